"""The demo's report page, rendered from constructed step markers and small figures.

The fixture writes what the demo's steps leave behind (markers, PNG figures, an H.264
overlay clip) without running them; the browser test opens the page in headless Chromium.
"""

from __future__ import annotations

import json
import re
from pathlib import Path

import numpy as np
from browser import broken_images, screenshot, video_state

from freipose.demo import report
from freipose.demo.context import DemoContext
from freipose.demo.markers import write_marker
from freipose.demo.presets import PRESETS
from freipose.demo.steps.analyze import _side_by_side
from freipose.demo.steps.evaluate import lift_note
from freipose.io.figures import new_figure, save_figure
from freipose.io.video import VideoWriter

FAILURE_MODES = {
    "pairs": [
        {"left": "Ear Left", "right": "Ear Right", "predicted_mm": 5.6, "true_mm": 28.3,
         "swap_rate": 0.42, "collapsed": True, "instants": 8},
        {"left": "Eye Left", "right": "Eye Right", "predicted_mm": 21.0, "true_mm": 23.5,
         "swap_rate": 0.05, "collapsed": False, "instants": 8},
    ],
    "bones": [{"bone": "Nose - Tail", "predicted_mm": 150.2, "true_mm": 171.9}],
    "warnings": ["Ear Left / Ear Right collapsed: predicted 5.6 mm apart, truly 28.3 mm"],
}  # fmt: skip


def _png(path: Path, title: str) -> str:
    fig = new_figure((3, 2))
    ax = fig.subplots()
    ax.plot([0, 1], [0, 1])
    ax.set_title(title)
    save_figure(fig, path, dpi=60)
    return str(path)


def _clip(path: Path) -> str:
    with VideoWriter(path, 25.0, (120, 80), codec="h264") as w:
        for i in range(10):
            img = np.full((80, 120, 3), 40, np.uint8)
            img[30:50, 5 * i : 5 * i + 20] = 220
            w.write(img)
    return str(path)


def _markers(out: Path, failure_modes: bool, smooth: bool) -> DemoContext:
    """Markers and figures of a finished demo run of the tiny preset (numbers made up)."""
    p = PRESETS["tiny"]
    ctx = DemoContext(out=out, preset=p)
    cal = out / "calibration"
    (cal / "report").mkdir(parents=True)
    (cal / "comparison.json").write_text(json.dumps({
        "cameras": ["cam0", "cam1"], "center_mm": [0.45, 1.31], "rotation_deg": [0.089, 0.073],
        "focal_percent": [[-0.31, -0.31], [0.24, 0.24]], "scale": 1.0016}))  # fmt: skip
    _png(cal / "comparison.png", "comparison")
    _png(cal / "report" / "rig_3d.png", "rig")
    summary = {"max_center_mm": 1.31, "max_rotation_deg": 0.089, "max_focal_percent": 0.31,
               "max_rms_px": 0.18}  # fmt: skip
    write_marker(out, p, "calibrate", {"summary": summary}, 10.0)
    write_marker(out, p, "labels", {
        "train": {"instants": 24, "median_reprojection_px": 0.93, "median_3d_vs_truth_mm": 3.5},
        "eval": {"instants": 8}}, 3.0)  # fmt: skip
    (out / "train" / "pose").mkdir(parents=True)
    (out / "train" / "config.toml").write_text("[schedule]\neval_samples = 4\n")
    _png(out / "train" / "pose" / "log.png", "log")
    detector = {"recall": 0.54, "recall_top1": 0.46, "median_center_error": 31.1,
                "center_rate": 1.0, "mean_agree": 6.35, "n_views": 280, "n_instants": 40,
                "cpu_fps": 446.6, "train_seconds": 27.6}  # fmt: skip
    last_log = {"val_jpe_p0": "20.86", "val_jpe_p1": "18.65"}
    trained = {"detector": {"metrics": detector}, "pose": {"last_log": last_log}}
    write_marker(out, p, "train", trained, 60.0)
    (out / "overlay").mkdir()
    predicted: dict = {"overlay": {
        "clip": _clip(out / "overlay" / "rat1_day2.mp4"),
        "frames": [_png(out / "overlay" / "rat1_day2_frame00020.png", "frame")],
        "start_s": 0.8, "end_s": 8.8, "stimulation_s": [[1.0, 3.0], [5.0, 7.0]]}}  # fmt: skip
    write_marker(out, p, "predict", predicted, 20.0)
    ev: dict = {
        "labels": {"voxel_P0": {"median": 21.22, "p30": 16.5, "p70": 28.7},
                   "voxel_P1": {"median": 18.72, "p30": 14.7, "p70": 26.8}},
        "pipeline": {"rat1_day2 (test)": {"median": 22.99, "missing": 0, "stimulated_part": {
            "stimulated": {"n": 40, "median_error_mm": 15.61, "median_height_error_mm": -11.2},
            "rest": {"n": 90, "median_error_mm": 9.47, "median_height_error_mm": -3.4},
            "lift_true_mm": 12.3, "lift_pred_mm": 5.1}},
                     "rat1_day3 (train)": {"median": 21.5, "missing": 0, "stimulated_part": {
            "stimulated": {"n": 40, "median_error_mm": 14.2, "median_height_error_mm": -7.0},
            "rest": {"n": 90, "median_error_mm": 9.1, "median_height_error_mm": -0.1},
            "lift_true_mm": 5.4, "lift_pred_mm": -1.6}}},
    }  # fmt: skip
    if failure_modes:
        ev["failure_modes"] = FAILURE_MODES
        ev["references"] = {"median pose at the held-out centre": {"median_mm": 41.5, "n": 96}}
        ev["comparisons"] = [{"a": "voxel_P1", "b": "baseline", "difference": -0.04,
                              "low": -0.16, "high": 0.07, "verdict": "not distinguishable",
                              "mean_difference": -0.15, "mean_low": -0.28, "mean_high": -0.05,
                              "mean_verdict": "lower", "win_rate": 0.66}]  # fmt: skip
    write_marker(out, p, "evaluate", ev, 5.0)
    analysis = {"classification": [
        {"animal": "rat1", "evaluated_on": "rat1", "balanced_accuracy": 0.43, "f1": 0.43,
         "p_value": 0.49, "n_effective": 54.3, "n_variables_used": 528,
         "train_balanced_accuracy": 1.0}],
        "top_variables": [{"variable": "local_z[Ear Right]", "part": "Ear Right", "f1": 0.66,
                           "p_value": 0.024, "p_adjusted": 1.0, "significant": False}],
        "top10_share_stimulated_part": 0.0, "significant": 0, "significant_variables": [],
        "balanced_accuracy": 0.43,
        "stimulated_best_rank": 4, "stimulated_best_variable": "local_z[Paw Front Right]",
        "stimulated_best_f1": 0.613}  # fmt: skip
    analyzed: dict = {"predicted": analysis}
    if smooth:
        sig = {"variable": "floor_dist_stft_3.12Hz[Tail]", "rank": 85, "f1": 0.574,
               "p_value": 2.1e-7, "p_adjusted": 1.1e-4}  # fmt: skip
        analyzed["smoothed"] = {**analysis, "balanced_accuracy": 0.554, "significant": 1,
                                "significant_variables": [sig], "stimulated_best_rank": 12,
                                "stimulated_best_f1": 0.5449}  # fmt: skip
        (out / "analysis").mkdir()
        analyzed["smooth"] = {"figure": _png(out / "analysis" / "smoothed_vs_raw.png", "smooth")}
    write_marker(out, p, "analyze", analyzed, 30.0)
    return ctx


def test_report_tables_name_their_columns(tmp_path):
    ctx = _markers(tmp_path / "demo", failure_modes=True, smooth=True)
    page = Path(report.run(ctx)["report"]).read_text()
    text = re.sub(r"<[^>]+>", " ", re.sub(r"<style>.*</style>", "", page, flags=re.S))
    text = re.sub(r"\s+", " ", text)
    # no raw dumps: the stimulation settings as a table, the detector's metrics by name
    assert "{" not in text and "frequency_hz" not in text and "median_center_error" not in text
    assert "oscillation frequency" in text and "5 Hz" in text and "20 mm" in text
    assert "boxes found" in text and "54.0 %" in text and "3D centre found" in text
    assert "446 images/s" not in text and "447 images/s" in text
    # explanations a reader asks for
    assert "pixel aspect ratio fixed" in text and "fx error" not in text
    assert "validates on 4 evenly spread of the 8 held-out" in text
    assert "p (unadjusted)" in text and "p (Bonferroni-adjusted)" in text
    assert "rat1_day3 (train day)" in text and "rat1_day2 (test day)" in text
    assert "rat1_day1 (labeling day: the training labels come from it; not analysed)" in text
    assert "best of 528 tries" in text
    assert "balanced accuracy on its training frames" in text
    assert re.search(r"rat1_day2 \(test day\) 0\.43 0\.43 0\.49 54\.3 1\b", text), text
    # failure modes: tables and the warning
    assert "Failure modes" in text and "Ear Left / Ear Right" in text
    assert re.search(r"Ear Left / Ear Right\s+5\.6\s+28\.3\s+42\.0 %\s+yes", text)
    assert "Nose - Tail" in text and "171.9" not in text and "172" in text
    assert 'class="warning"' in page and "collapsed: predicted 5.6 mm" in text
    assert "median pose at the held-out centre" in text
    assert "height change predicted (mm)" in text
    assert re.search(r"rat1_day2 \(test\) 15\.6 9\.5 -11\.2 -3\.4 \+5\.1 \+12\.3", text), text
    # the paired comparison: both statistics with their intervals and verdicts
    assert "Paired comparisons" in text
    row = r"2D views\) vs baseline .{0,60}-0\.04 \(-0\.16 to \+0\.07\): not distinguishable"
    assert re.search(row + r" -0\.15 \(-0\.28 to -0\.05\): lower 66 %", text)
    # the overlay video embedded, the smoothing figure shown, every path relative
    assert '<video controls preload="auto" src="overlay/rat1_day2.mp4">' in page
    assert 'src="analysis/smoothed_vs_raw.png"' in page
    assert str(tmp_path) not in page
    assert "http://" not in page and "https://" not in page  # nothing fetched


def _text(page: str) -> str:
    """The page's visible text, whitespace collapsed."""
    text = re.sub(r"<[^>]+>", " ", re.sub(r"<style>.*</style>", "", page, flags=re.S))
    return re.sub(r"\s+", " ", text)


def test_report_shows_raw_vs_smoothed_as_the_terminal_does(tmp_path):
    ctx = _markers(tmp_path / "demo", failure_modes=False, smooth=True)
    page = Path(report.run(ctx)["report"]).read_text()
    text = _text(page)
    assert "Raw vs smoothed predictions" in text and 'href="#smoothing"' in page
    marker = json.loads((tmp_path / "demo" / ".demo" / "analyze.done").read_text())["results"]
    printed = _side_by_side(marker["predicted"], marker["smoothed"])
    # every line the terminal prints is a row of the report's table, with the same numbers
    lines = [ln.strip() for ln in printed.splitlines()[1:]]
    assert len(lines) == 4
    for line in lines:
        name, values = line.split(": ", 1)
        raw, smoothed = values.split(" vs ")
        assert f"{name} {raw} {smoothed}" in text, (line, text)
    assert "balanced accuracy of the classifier on the test day 0.43 0.55" in text
    sig = "significant single variables 0 1 (floor_dist_stft_3.12Hz[Tail], rank 85, F1 0.57)"
    assert sig in text
    assert "local_z[Paw Front Right] (rank 4, F1 0.61) local_z[Paw Front Right] (rank 12" in text
    assert 'src="analysis/smoothed_vs_raw.png"' in page


def test_report_names_the_significant_variables(tmp_path):
    ctx = _markers(tmp_path / "demo", failure_modes=False, smooth=True)
    text = _text(Path(report.run(ctx)["report"]).read_text())
    smoothed = text.split("On the smoothed predicted poses")[1]
    assert "1 significant after the adjustment, listed below the table" in smoothed
    row = "floor_dist_stft_3.12Hz[Tail] 85 0.574 2.1e-07 0.00011"
    assert "The 1 significant variable (rank: place by F1 among all 528): " in smoothed
    assert f"p (Bonferroni-adjusted) {row}" in smoothed
    predicted = text.split("On the predicted poses")[1].split("On the smoothed")[0]
    assert "0 significant after the adjustment)" in predicted
    assert "significant variable (rank" not in predicted
    assert (
        '"Significant": the adjusted p-value is below 0.001 and the balanced accuracy above'
        in predicted
    )


def test_report_names_significant_variables_of_an_older_marker_from_its_results(tmp_path):
    ctx = _markers(tmp_path / "demo", failure_modes=False, smooth=False)
    marker = tmp_path / "demo" / ".demo" / "analyze.done"
    doc = json.loads(marker.read_text())
    del doc["results"]["predicted"]["significant_variables"]  # written before the list
    doc["results"]["predicted"]["significant"] = 1
    marker.write_text(json.dumps(doc))
    res = tmp_path / "demo" / "analysis" / "results"
    res.mkdir(parents=True)
    (res / "attribution.csv").write_text(
        "variable,part,f1,p_value,p_adjusted,significant\n"
        "local_z[Tail],Tail,0.61,1e-6,0.0005,True\n"
        "local_x[Nose],Nose,0.70,0.01,1.0,False\n"
        "local_y[Nose],Nose,0.65,0.02,1.0,False\n"
    )
    text = _text(Path(report.run(ctx)["report"]).read_text())
    assert "p (Bonferroni-adjusted) local_z[Tail] 3 0.61 1e-06 0.0005" in text


def test_report_says_when_the_predicted_lift_disagrees(tmp_path):
    ctx = _markers(tmp_path / "demo", failure_modes=False, smooth=False)
    page = Path(report.run(ctx)["report"]).read_text()
    text = _text(page)
    flip = ("The network does not reproduce the height change on rat1_day3 (train): predicted "
            "-1.6 mm, true +5.4 mm (the opposite direction).")  # fmt: skip
    assert flip in text
    part = ("reproduces only part of the height change on rat1_day2 (test): predicted +5.1 mm, "
            "true +12.3 mm")  # fmt: skip
    assert part in text
    # next to the table: after it, before the next section's figures
    table_end = text.index("+5.1 +12.3")
    assert table_end < text.index(flip) < text.index("Overlay")
    assert page.count('<p class="warning">The network') == 2


def test_lift_note_only_when_prediction_and_truth_disagree():
    def note(pred, true):
        return lift_note("day", {"lift_pred_mm": pred, "lift_true_mm": true})

    assert note(5.0, 5.4) is None and note(4.0, 5.4) is None  # within half the true lift
    assert note(-0.3, 0.4) is None  # both within 1 mm of each other: no lift either way
    assert note(None, 5.4) is None and lift_note("day", {}) is None
    assert "does not reproduce" in note(-1.6, 5.4) and "opposite" in note(3.0, -4.0)
    assert "only part" in note(2.0, 5.4) and "exaggerates" in note(9.0, 5.4)


def test_report_says_which_stimulation_windows_the_clip_shows(tmp_path):
    ctx = _markers(tmp_path / "demo", failure_modes=False, smooth=False)
    text = _text(Path(report.run(ctx)["report"]).read_text())
    assert ("The clip runs from 0.8 s to 8.8 s of the recording; the Paw Front Right is "
            "stimulated from 1.0 to 3.0 s and from 5.0 to 7.0 s.") in text  # fmt: skip


def test_report_without_optional_sections(tmp_path):
    ctx = _markers(tmp_path / "demo", failure_modes=False, smooth=False)
    page = Path(report.run(ctx)["report"]).read_text()
    assert "Raw vs smoothed" not in page and "smoothed_vs_raw" not in page
    assert "Failure modes" not in page and "Smoothing" not in page
    assert "For comparison" not in page and "Paired comparisons" not in page
    assert "Figure not written: <code>train/baseline/log.png</code>" in page


def test_report_unequal_focal_errors_get_two_columns(tmp_path):
    ctx = _markers(tmp_path / "demo", failure_modes=False, smooth=False)
    comp = tmp_path / "demo" / "calibration" / "comparison.json"
    doc = json.loads(comp.read_text())
    doc["focal_percent"] = [[-0.31, -0.2], [0.24, 0.3]]
    comp.write_text(json.dumps(doc))
    page = Path(report.run(ctx)["report"]).read_text()
    assert "f<sub>x</sub> error (%)" in page and "pixel aspect ratio fixed" not in page


def test_report_loads_in_chromium(tmp_path, chromium):
    ctx = _markers(tmp_path / "demo", failure_modes=True, smooth=True)
    path = Path(report.run(ctx)["report"])
    chromium.get(path.as_uri())
    assert broken_images(chromium) == []
    n_images = chromium.execute_script("return document.images.length")
    assert n_images == 5  # comparison, rig, pose log, overlay frame, smoothing
    state = video_state(chromium)
    assert state["error"] is None and state["readyState"] >= 2, state
    assert state["videoWidth"] == 120
    shot = screenshot(chromium, tmp_path / "report.png")
    assert shot.stat().st_size > 0
