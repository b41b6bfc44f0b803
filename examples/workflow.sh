#!/usr/bin/env bash
# The FreiPose workflow, command by command, on the demo's synthetic data.
#
# `freipose demo` runs the same steps through the library and writes a report; this script
# shows the commands you run on your own recordings. Usage:
#
#   examples/workflow.sh [WORKDIR]            # default WORKDIR: freipose_workflow
#   FRAMES=100 STEPS=4 DETECTION=bgsub examples/workflow.sh   # a quick smoke run
#
# (A few-step detector finds nothing; DETECTION=bgsub predicts with background subtraction.)
#
# Sizes follow `freipose demo --preset small`. Every command resumes or skips finished work
# when the script is run again (synth keeps rendered videos, train needs --resume, predict
# skips complete outputs, analyze reuses cached variables).
set -euo pipefail

W=${1:-freipose_workflow}
FRAMES=${FRAMES:-750}           # frames per session (25 fps)
CALIB_FRAMES=${CALIB_FRAMES:-80}
STEPS=${STEPS:-1000}            # voxel network and baseline steps (the detector gets 1/4)
DETECTION=${DETECTION:-detector}  # how predict finds the animal: detector or bgsub
mkdir -p "$W/scenes"

echo "== 1. Synthesize: a calibration recording and three stimulated sessions (7 cameras)"
# Scene files fix every setting; jitter_rig = false gives all sessions the same rig, and
# animal_seed = 1 the same rat. Day 1 gives the training labels, day 3 trains the
# stimulation classifier and day 2 is held out.
for s in 1 2 3; do
  calib=false; [ "$s" = 1 ] && calib=true
  cat > "$W/scenes/rat1_day$s.toml" <<EOF
[scene]
n_cameras = 7
frames = $FRAMES
fps = 25.0
size = [320, 256]
seed = $s
animal_seed = 1
appearance = "hooded"
calibration_video = $calib
calibration_frames = $CALIB_FRAMES
jitter_rig = false

[scene.stimulation]
body_part = "Paw Front Right"
effect = "oscillate"
frequency_hz = 5.0
amplitude_mm = 30.0
duration_s = 2.0
spacing_s = 2.0
onset_s = 1.0
EOF
  freipose synth "$W/recordings/rat1_day$s" --config "$W/scenes/rat1_day$s.toml"
done

echo "== 2. Calibrate the cameras from the board videos (world: the board on the floor, frame 0)"
CAL="$W/recordings/rat1_day1/calibration"
freipose calib "$CAL"/cam*.mp4 --board "$CAL/board.toml" --origin-frame 0 \
    -o "$W/calibration.toml" --report "$W/calibration_report"
freipose calib show "$W/calibration.toml"

echo "== 3. Labels: 2D labels of a few hundred instants, triangulated with the calibration"
# Stands in for your labelling tool's export + `freipose labels import`: the synthetic 2D
# labels of the visible keypoints (1 px noise) go through the labels library's importer.
python - "$W" <<'EOF'
import sys
from pathlib import Path

import numpy as np

from freipose.io.calibration import load_calibration
from freipose.io.labels import read_labels_h5, write_labels_h5
from freipose.labels.importing import ImportOptions, SourceLabels, build_labelset

w = Path(sys.argv[1])
rig = load_calibration(w / "calibration.toml")
rng = np.random.default_rng(0)
for session, n, out in (("rat1_day1", 300, "train.h5"), ("rat1_day2", 60, "eval.h5")):
    folder = w / "recordings" / session
    lab = read_labels_h5(folder / "labels.h5")
    sub = lab.select(np.unique(np.linspace(0, len(lab) - 1, n).round().astype(int)))
    vis = sub.visible2d
    p2 = np.where(vis[..., None], sub.points2d, np.nan) + rng.normal(0, 1.0, sub.points2d.shape)
    info = sub.sessions[session]
    src = SourceLabels(
        source=str(folder), session=session, cameras=list(sub.cameras),
        keypoints=list(sub.keypoints), frame_index=sub.frame_index, points2d=p2,
        visible2d=vis, videos={c: folder / v for c, v in info.videos.items()}, fps=info.fps,
    )
    path = w / "labels" / out
    path.parent.mkdir(parents=True, exist_ok=True)
    labels = build_labelset([src], ImportOptions(calibration=rig, threshold=8.0), path)
    write_labels_h5(labels, path)
    print(f"wrote {path}: {len(labels)} instants")
EOF

echo "== 4. Train the detector, the voxel network and the triangulation baseline"
cat > "$W/train.toml" <<EOF
[data]
labels = "labels/train.h5"
eval_labels = "labels/eval.h5"
skeleton = "rat"

[model]
preset = "small"

[schedule]
steps = $STEPS
lr = 1e-3
lr_decay_steps = $(( STEPS * 2 / 3 > 0 ? STEPS * 2 / 3 : 1 ))
refine_start = 0.0
checkpoint_every = 100
eval_every = 500
eval_samples = 16

[augment]
max_views = 4

[detector]
input_size = 128
width = 0.35
neck_channels = 24
steps = $(( STEPS / 4 > 0 ? STEPS / 4 : 1 ))
batch_size = 8
checkpoint_every = 50
max_images = 1400
max_eval_instants = 40
warmup_steps = 20
cube_size = 320.0
EOF
resume() { [ -f "$1" ] && echo --resume || true; }
[ -f "$W/runs/detector/detector.pt" ] || freipose train "$W/train.toml" --stage detector \
    --out "$W/runs/detector" $(resume "$W/runs/detector/detector_last.pt")
[ -f "$W/runs/pose/model.pt" ] || freipose train "$W/train.toml" --out "$W/runs/pose" \
    $(resume "$W/runs/pose/checkpoint.pt")
[ -f "$W/runs/baseline/model.pt" ] || freipose train "$W/train.toml" \
    --stage baseline --out "$W/runs/baseline" $(resume "$W/runs/baseline/checkpoint.pt")

echo "== 5. Evaluate on the held-out labels: voxel network vs. triangulation baseline"
freipose eval "$W/runs/pose/model.pt" "$W/labels/eval.h5" \
    --baseline "$W/runs/baseline/model.pt" -o "$W/eval"

echo "== 6. Predict the analysed sessions, render an overlay clip, export a table"
if [ "$DETECTION" = bgsub ]; then
  find_animal=(--method bgsub)
else
  find_animal=(--detector "$W/runs/detector/detector.pt")
fi
freipose predict "$W/recordings/rat1_day2" "$W/recordings/rat1_day3" \
    --model "$W/runs/pose/model.pt" "${find_animal[@]}" \
    --calibration "$W/calibration.toml" -o "$W/poses"
freipose render "$W/recordings/rat1_day2" "$W/poses/rat1_day2.poses.h5" \
    -o "$W/overlay_rat1_day2.mp4" --frames 20:70
freipose export "$W/poses/rat1_day2.poses.h5" --format csv -o "$W/rat1_day2.csv"

echo "== 7. Analyze: which body part does the stimulation change?"
# The classifier trains on day 3, not on day 1: the network fits its labeled frames best,
# and a classifier trained on them would not carry over to other days (docs/own-data.md).
cat > "$W/study.toml" <<EOF
skeleton = "rat"

[[recordings]]
name = "rat1_day3"
poses = "poses/rat1_day3.poses.h5"
events = "recordings/rat1_day3/events.csv"
animal = "rat1"
condition = "paw_stimulation"
split = "train"

[[recordings]]
name = "rat1_day2"
poses = "poses/rat1_day2.poses.h5"
events = "recordings/rat1_day2/events.csv"
animal = "rat1"
condition = "paw_stimulation"
split = "test"
EOF
freipose analyze "$W/study.toml" -o "$W/analysis" --stft-window 32 --onset-delay 0.6 \
    --margin 0.5 --pre 1 --post 1
echo "done: see $W/eval, $W/overlay_rat1_day2.mp4 and $W/analysis"
