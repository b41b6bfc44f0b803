"""A full disk or a read-only output folder: every command says which path and what to do,
never shows a traceback or crashes, leaves nothing under a final name, and completes when
run again after the cause is removed.

The folders are real filesystems: a read-only tmpfs and a 4 MB tmpfs filled to the last
byte. Mounting them needs root (CAP_SYS_ADMIN); the tests skip with the reason elsewhere.
Commands run in a child process, so that a crash (HDF5 on a full disk killed the process
with SIGSEGV) fails the test instead of the test run.
"""

from __future__ import annotations

import os
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path

import h5py
import numpy as np
import pytest

REPO = Path(__file__).resolve().parents[1]
PREDICT_HELPERS = REPO / "tests" / "predict"
sys.path.insert(0, str(PREDICT_HELPERS))

from predict_helpers import BlobEstimator, h5_equal, make_session  # noqa: E402

from freipose.io.poses import PoseData, write_poses_h5  # noqa: E402
from freipose.io.session import discover_sessions  # noqa: E402
from freipose.predict.run import predict_session  # noqa: E402
from freipose.skeleton import load_skeleton  # noqa: E402

T = 24
KW = {"batch_size": 4, "chunk_frames": 8, "progress": False}

# `freipose ARGS...` in a child process; predict runs the blob estimator of the prediction
# tests instead of a network (the writer, the locks and the messages are the real ones).
# Only predict imports the network module (and with it PyTorch): the other commands start
# as a user's would.
CLI = f"""
import sys
if sys.argv[1] == "predict":
    sys.path.insert(0, {str(PREDICT_HELPERS)!r})
    import freipose.io.checkpoints, freipose.predict.network
    from predict_helpers import BlobEstimator
    from freipose.predict.run import predict_session

    def fake(sessions, model, spec, outdir, *, shard=None, overwrite=False, report=None, **kw):
        out = []
        for s in sessions:
            r = predict_session(s, BlobEstimator(), outdir, shard=shard, overwrite=overwrite,
                                batch_size=4, chunk_frames=8, progress=False)
            report(r)
            out.append(r)
        return out

    freipose.io.checkpoints.check_checkpoints = lambda *a: None
    freipose.predict.network.predict_sessions = fake
from freipose.cli.main import cli
cli(sys.argv[1:], prog_name="freipose")
"""


def _mount(folder: Path, options: str) -> None:
    subprocess.run(["mount", "-t", "tmpfs", "-o", options, "tmpfs", str(folder)],
                   check=True, capture_output=True, text=True)  # fmt: skip


def _umount(folder: Path) -> None:
    subprocess.run(["umount", str(folder)], check=True, capture_output=True)


@pytest.fixture(scope="module")
def mounts(tmp_path_factory: pytest.TempPathFactory) -> None:
    """Skip unless this process may mount a tmpfs (root with CAP_SYS_ADMIN)."""
    probe = tmp_path_factory.mktemp("probe")
    try:
        _mount(probe, "size=64k")
    except (OSError, subprocess.CalledProcessError) as exc:
        why = getattr(exc, "stderr", "") or exc
        pytest.skip(f"cannot mount a tmpfs here (needs root with CAP_SYS_ADMIN): {why}")
    _umount(probe)


@pytest.fixture
def read_only(tmp_path: Path, mounts: None) -> Iterator[Path]:
    """A folder on a read-only filesystem (root cannot write there either)."""
    folder = tmp_path / "ro"
    folder.mkdir()
    _mount(folder, "ro,size=1m")
    yield folder
    _umount(folder)


class FullDisk:
    """A small filesystem whose free space a filler file takes."""

    def __init__(self, folder: Path):
        self.folder = folder
        self.filler = folder / "filler"

    def fill(self) -> None:
        """Take every free byte."""
        with open(self.filler, "ab", buffering=0) as f:
            try:
                while True:
                    f.write(b"\0" * 1024)
            except OSError:
                pass

    def free(self) -> None:
        """Give the space back."""
        self.filler.unlink()

    def files(self) -> list[str]:
        """Every file on it but the filler (relative names)."""
        return sorted(
            str(p.relative_to(self.folder))
            for p in self.folder.rglob("*")
            if p.is_file() and p != self.filler
        )


@pytest.fixture
def full_disk(tmp_path: Path, mounts: None) -> Iterator[FullDisk]:
    """A full 4 MB filesystem."""
    folder = tmp_path / "full"
    folder.mkdir()
    _mount(folder, "size=4m")
    disk = FullDisk(folder)
    disk.fill()
    yield disk
    _umount(folder)


@pytest.fixture(scope="module")
def data(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    """A 24-frame session, its poses, a labels file, a rat's poses and a training config."""
    root = tmp_path_factory.mktemp("inputs")
    make_session(root / "rec", T)
    (s,) = discover_sessions([root / "rec"])
    poses = predict_session(s, BlobEstimator(), root / "poses", **KW).path
    syn = root / "syn"
    res = _freipose("synth", syn, "--frames", 12, "--cameras", 2, "--size", "64x48")
    assert res.returncode == 0, res.stderr
    rat = load_skeleton("rat")
    rng = np.random.default_rng(0)
    walk = np.cumsum(rng.normal(0, 2, (60, 1, 3)), 0) + rng.normal(0, 30, (1, 12, 3))
    rat_poses = root / "rat.poses.h5"
    conf = np.ones((60, 12), np.float32)
    pose = PoseData(walk.astype(np.float32), conf, rat.keypoints, np.arange(60), 30.0, skeleton=rat)
    write_poses_h5(pose, rat_poses)
    with h5py.File(rat_poses, "a") as f:
        f.attrs["complete"] = True
    config = root / "tiny.toml"
    config.write_text(
        f'[data]\nlabels = "{syn / "labels.h5"}"\nskeleton = "rat"\n[model]\npreset = "tiny"\n'
        "[schedule]\nsteps = 1\nbatch_size = 2\ncheckpoint_every = 1\neval_every = 1\n"
        "[augment]\nenabled = false\n"
    )
    shards = root / "shards"
    for i in range(2):
        predict_session(s, BlobEstimator(), shards, shard=(i, 2), **KW)
    return {"session": root / "rec", "poses": poses, "labels": syn / "labels.h5",
            "rat": rat_poses, "config": config, "shards": shards, "model": poses}  # fmt: skip


def _freipose(*args: object) -> subprocess.CompletedProcess:
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    cmd = [sys.executable, "-c", CLI, *map(str, args)]
    return subprocess.run(cmd, capture_output=True, text=True, env=env, timeout=600)


# command -> (arguments with {out} for the output folder, what it writes there)
COMMANDS = {
    "predict": (["predict", "{session}", "--model", "{model}", "-o", "{out}/poses",
                 "--method", "bgsub"], "poses/rec.poses.h5"),
    "smooth": (["smooth", "{poses}", "-o", "{out}/sm"], "sm/rec.poses.h5"),
    "export": (["export", "{poses}", "-o", "{out}/p.csv"], "p.csv"),
    "export-nwb": (["export", "{poses}", "-o", "{out}/p.nwb", "--format", "nwb"], "p.nwb"),
    "render": (["render", "{session}", "{poses}", "-o", "{out}/o.mkv", "--frames", "0:8",
                "--tile-width", "64"], "o.mkv"),
    "merge": (["merge", "{shards}", "-o", "{out}"], "rec.poses.h5"),
    "labels-split": (["labels", "split", "{labels}", "--by", "time", "--gap", "0",
                      "-o", "{out}/tr.h5", "{out}/ev.h5"], "tr.h5"),
    "analyze": (["analyze", "variables", "{rat}", "-o", "{out}/v.h5"], "v.h5"),
    "synth": (["synth", "{out}/syn", "--frames", "3", "--cameras", "2", "--size", "64x48"],
              "syn/labels.h5"),
}  # fmt: skip
SLOW = {"train": (["train", "{config}", "--out", "{out}/run"], "run/model.pt")}


def _args(name: str, data: dict[str, Path], out: Path) -> list[str]:
    args, _ = {**COMMANDS, **SLOW}[name]
    return [a.format(out=out, **data) for a in args]


def _says(res: subprocess.CompletedProcess, *words: str) -> None:
    """One message, no traceback, exit status 1."""
    text = res.stdout + res.stderr
    assert res.returncode == 1, (res.returncode, text[-3000:])
    assert "Traceback" not in text and "Segmentation" not in text, text[-3000:]
    for w in words:
        assert w in text, text[-3000:]


@pytest.mark.slow
@pytest.mark.parametrize("name", sorted(COMMANDS))
def test_read_only_folder(name, data, read_only):
    res = _freipose(*_args(name, data, read_only))
    _says(res, f"cannot write {read_only}", "read-only filesystem", "run the command again")
    assert not any(read_only.iterdir())


def _full_then_freed(name: str, data: dict[str, Path], disk: FullDisk) -> None:
    out = _args(name, data, disk.folder)
    res = _freipose(*out)
    _says(res, f"cannot write {disk.folder}", "free space there", "run the command again")
    assert disk.files() == [], "something was left on the full disk"
    disk.free()
    res = _freipose(*out)
    assert res.returncode == 0, res.stdout + res.stderr
    assert (disk.folder / COMMANDS.get(name, SLOW.get(name))[1]).is_file()


@pytest.mark.slow
@pytest.mark.parametrize("name", sorted(COMMANDS))
def test_full_disk_then_freed(name, data, full_disk):
    _full_then_freed(name, data, full_disk)


def test_label_command_refuses_a_read_only_or_full_folder(data, read_only, full_disk):
    """``freipose label`` says so before it starts its server (a rerun then serves the page)."""
    syn = data["labels"].parent
    args = ["label", syn, "--calibration", syn / "true_calibration.toml", "--skeleton", "rat",
            "--no-browser", "-o"]  # fmt: skip
    _says(_freipose(*args, read_only / "labels.h5"), f"cannot write {read_only}", "read-only")
    _says(_freipose(*args, full_disk.folder / "labels.h5"), "is full", "free space there")
    assert full_disk.files() == []


@pytest.mark.slow
def test_train_full_disk_and_read_only(data, full_disk, read_only):
    res = _freipose(*_args("train", data, read_only))
    _says(res, f"cannot write {read_only}", "read-only filesystem")
    _full_then_freed("train", data, full_disk)


FILL_DURING = f"""
import sys
sys.path.insert(0, {str(PREDICT_HELPERS)!r})
from pathlib import Path
from predict_helpers import BlobEstimator
from freipose.errors import OutputWriteError
from freipose.io.session import discover_sessions
from freipose.predict.run import predict_session

session, out, filler = sys.argv[1:]

def fill(rows):
    if rows == 8:
        with open(filler, "ab", buffering=0) as f:
            try:
                while True:
                    f.write(bytes(1024))
            except OSError:
                pass

(s,) = discover_sessions([session])
try:
    predict_session(s, BlobEstimator(), out, batch_size=4, chunk_frames=8, progress=False,
                    on_batch=fill)
except OutputWriteError as exc:
    print("stopped:", exc)
"""


def test_predict_disk_filling_during_the_run(data, full_disk):
    """The disk fills between two chunks: a clean error, no partial file; then it completes."""
    full_disk.free()
    out = full_disk.folder / "poses"
    cmd = [sys.executable, "-c", FILL_DURING, data["session"], out, full_disk.filler]
    res = subprocess.run(list(map(str, cmd)), capture_output=True, text=True, timeout=300)
    assert res.returncode == 0, res.stderr[-3000:]
    stopped = f"stopped: cannot write {out / 'rec.poses.h5'}: its next rows take up to"
    assert stopped in res.stdout and "free space there" in res.stdout, res.stdout
    assert full_disk.files() == []
    full_disk.free()
    (s,) = discover_sessions([data["session"]])
    r = predict_session(s, BlobEstimator(), out, **KW)
    assert r.frames == T and h5_equal(r.path, data["poses"]) == []


def _killed_partial(data: dict[str, Path], out: Path) -> Path:
    """The partial file of a run killed after 16 of 24 frames."""

    class Killed(Exception):
        pass

    def kill(rows: int) -> None:
        if rows >= 16:
            raise Killed

    (s,) = discover_sessions([data["session"]])
    with pytest.raises(Killed):
        predict_session(s, BlobEstimator(), out, on_batch=kill, **KW)
    (partial,) = out.glob("*.partial")
    return partial


def test_predict_starts_a_damaged_partial_file_again(data, tmp_path, caplog):
    partial = _killed_partial(data, tmp_path)
    with h5py.File(partial, "r") as f:  # overwrite the last committed chunk of the poses
        d = f["poses"]
        info = d.id.get_chunk_info(d.id.get_num_chunks() - 1)
    with open(partial, "r+b") as f:
        f.seek(info.byte_offset)
        f.write(b"\xff" * info.size)
    (s,) = discover_sessions([data["session"]])
    r = predict_session(s, BlobEstimator(), tmp_path, **KW)
    assert f"the partial file {partial} from an interrupted run is damaged" in caplog.text
    assert r.frames == T and h5_equal(r.path, data["poses"]) == []


def test_predict_overwrite_never_resumes(data, tmp_path):
    _killed_partial(data, tmp_path)
    (s,) = discover_sessions([data["session"]])
    r = predict_session(s, BlobEstimator(), tmp_path, overwrite=True, **KW)
    assert r.frames == T and h5_equal(r.path, data["poses"]) == []


def test_predict_shards_fewer_frames_than_shards_then_merge(data, tmp_path):
    """24 frames in chunks of 8 are 3 chunks: 5 of 8 shards are empty, and merge joins all."""
    (s,) = discover_sessions([data["session"]])
    for i in range(8):
        r = predict_session(s, BlobEstimator(), tmp_path / "shards", shard=(i, 8), **KW)
        assert r.frames == (8 if i in (2, 5, 7) else 0)
    res = _freipose("merge", tmp_path / "shards", "-o", tmp_path / "merged")
    assert res.returncode == 0, res.stdout + res.stderr
    merged = tmp_path / "merged" / "rec.poses.h5"
    assert h5_equal(merged, data["poses"]) == []
    with h5py.File(merged) as f, h5py.File(data["poses"]) as g:
        assert f["poses"].chunks == g["poses"].chunks and f["poses"].compression == "gzip"


def test_label_page_save_on_a_full_disk(full_disk):
    """507 with what to do; the file keeps the earlier save; after freeing space it saves."""
    from starlette.testclient import TestClient

    from freipose.io.labels import read_labels_h5
    from freipose.labelui.app import create_app
    from freipose.labelui.frames import FrameCache
    from freipose.labelui.startup import open_store
    from freipose.synth import SceneConfig, generate_session

    full_disk.free()
    folder = full_disk.folder.parent / "rat1"
    cfg = SceneConfig(n_cameras=2, frames=4, size=(64, 48), seed=3, motion_blur=False)
    paths = generate_session(folder, cfg, workers=1, progress=False)
    out = full_disk.folder / "labels.h5"
    store = open_store([folder], paths.calibration, "rat", out, per_session=2)
    frames = FrameCache(store.sessions, store.instants)
    h = {"X-FreiPose-Token": "t"}

    def save(version: int, state: str) -> object:
        body = {"version": version, "labels": {"cam0": {"Tail": {"state": state}}}}
        return client.post("/api/instant/0", json=body, headers=h)

    try:
        with TestClient(create_app(store, frames, "t")) as client:
            assert save(0, "occluded").status_code == 200
            before = out.read_bytes()
            full_disk.fill()
            r = save(1, "notinview")
            assert r.status_code == 507, r.text
            msg = r.json()["error"]
            assert f"cannot write {out}: the disk holding {full_disk.folder} is full" in msg
            assert "save again; your edits are kept in this page" in msg
            assert out.read_bytes() == before and full_disk.files() == ["labels.h5"]
            assert client.get("/api/instant/0", headers=h).json()["version"] == 1
            full_disk.free()
            assert save(1, "notinview").status_code == 200
    finally:
        frames.close()
    assert read_labels_h5(out).session.shape == (1,)
