"""The label server's file and the other writers: one lock by the real path, links kept."""

from __future__ import annotations

import contextlib
import re
import signal
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path

import httpx
import numpy as np
from click.testing import CliRunner

from freipose.cli.main import cli
from freipose.io.labels import read_labels_h5, write_labels_h5
from freipose.io.lock import lock_path
from freipose.labelui.geometry import VISIBLE
from freipose.labelui.server import network_warning
from freipose.labelui.startup import open_store


@contextlib.contextmanager
def _label_server(
    session, out: Path, *extra: str
) -> Iterator[tuple[subprocess.Popen, str, list[str]]]:
    """``freipose label`` in a subprocess, stopped (Ctrl-C) after the block.

    Yields the process, the page's URL and its output lines (complete after the block).
    """
    proc = subprocess.Popen(
        [sys.executable, "-m", "freipose.cli.main", "label", str(session.folder),
         "--calibration", str(session.calibration), "--skeleton", "rat", "-o", str(out),
         "--no-browser", *extra],
        stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
    )  # fmt: skip
    lines: list[str] = []
    try:
        end = time.monotonic() + 30
        url = None
        while url is None and time.monotonic() < end:
            line = proc.stdout.readline()
            if not line and proc.poll() is not None:
                break
            lines.append(line)
            m = re.search(r"open (http://\S+)", line)
            url = m.group(1) if m else None
        assert url is not None, "".join(lines)
        url = re.sub(r"^http://[^/]+:", "http://127.0.0.1:", url)  # --host 0.0.0.0: a name
        while time.monotonic() < end:  # until it serves
            with contextlib.suppress(httpx.HTTPError):
                if httpx.get(url).status_code == 200:
                    break
            time.sleep(0.1)
        yield proc, url, lines
    finally:
        proc.send_signal(signal.SIGINT)
        rest, _ = proc.communicate(timeout=20)
        lines.append(rest)


def _invoke(*args: object):
    return CliRunner().invoke(cli, [str(a) for a in args])


def test_labels_commands_refused_while_the_server_runs(synth_session, tmp_path):
    s = synth_session
    a, b, live = tmp_path / "a.h5", tmp_path / "b.h5", tmp_path / "live.h5"
    write_labels_h5(s.truth.select(np.arange(0, 6)), a)
    write_labels_h5(s.truth.select(np.arange(6, 12)), b)
    write_labels_h5(s.truth.select([0, 4, 7]), live)
    before = live.read_bytes()
    (tmp_path / "poses").mkdir()
    with _label_server(s, live) as (proc, _, lines):
        refused = {
            "merge": _invoke("labels", "merge", a, b, "-o", live),
            "split": _invoke("labels", "split", a, "-o", tmp_path / "tr.h5", live),
            "boxes": _invoke("labels", "boxes", a, "-o", live),
            "import": _invoke("labels", "import", "--format", "dlc", s.folder, "-o", live),
            "select": _invoke("labels", "select", s.folder, "--calibration", s.calibration,
                              "--poses-dir", tmp_path / "poses", "-o", live),
        }  # fmt: skip
        for name, res in refused.items():
            assert res.exit_code == 1, (name, res.output)
            assert "in use by another run: `" in res.output, (name, res.output)
            assert f"main.py label {s.folder} --calibration" in res.output, (name, res.output)
            assert f"pid {proc.pid}" in res.output and "Ctrl-C" in res.output, name
            assert "Traceback" not in res.output
        assert live.read_bytes() == before
        assert not (tmp_path / "tr.h5").exists()  # nothing written, not even the other part
    assert read_labels_h5(live).frame_index.tolist() == [0, 4, 7]  # resumed and kept
    res = _invoke("labels", "merge", a, b, "-o", live)  # once the server has stopped
    assert res.exit_code == 0 and len(read_labels_h5(live)) == 12, res.output


def test_a_link_shares_its_targets_lock_and_stays_a_link(synth_session, tmp_path):
    s = synth_session
    target, link = tmp_path / "labels.h5", tmp_path / "link.h5"
    write_labels_h5(s.truth.select([0, 4]), target)
    link.symlink_to(target.name)
    with _label_server(s, target) as (proc, _, lines):
        res = _invoke("label", s.folder, "--calibration", s.calibration, "--skeleton", "rat",
                      "-o", link, "--no-browser")  # fmt: skip
        assert res.exit_code == 1 and "in use by another run" in res.output, res.output
        assert f"pid {proc.pid}" in res.output
        res = _invoke("labels", "merge", target, "-o", link)
        assert res.exit_code == 1 and "in use by another run" in res.output, res.output
    assert not lock_path(link).exists() and not lock_path(target).exists()
    # a save through the link writes the target and leaves the link a link
    store = open_store([s.folder], s.calibration, "rat", link, per_session=4)
    i = [x.frame for x in store.instants].index(11)
    V, K = len(store.cameras), store.skeleton.num_keypoints
    pts = np.full((V, K, 2), np.nan)
    status = np.zeros((V, K), np.int8)
    pts[0, 0], status[0, 0] = (50.0, 60.0), VISIBLE
    store.save(i, 0, pts, status)
    assert link.is_symlink() and link.resolve() == target.resolve()
    assert read_labels_h5(target).frame_index.tolist() == [0, 4, 11]
    write_labels_h5(s.truth.select([1]), link)  # every writer writes through
    assert link.is_symlink() and read_labels_h5(target).frame_index.tolist() == [1]


def test_stop_says_whether_anything_was_saved(synth_session, tmp_path):
    out = tmp_path / "labels.h5"
    with _label_server(synth_session, out) as (proc, _, lines):
        pass
    said = "".join(lines)
    assert "no edits; nothing saved" in said and "labels saved" not in said, said
    assert not out.exists()
    with _label_server(synth_session, out) as (proc, url, lines):
        body = {"version": 0, "labels": {"cam0": {"Nose": {"state": "occluded"}}}}
        r = httpx.post(url.replace("/?", "/api/instant/0?"), json=body)
        assert r.status_code == 200, r.text
    said = "".join(lines)
    assert f"labels saved in {out} (1 edit)" in said, said
    with _label_server(synth_session, out) as (proc, _, lines):
        pass
    said = "".join(lines)
    assert f"no edits; {out} left as it was" in said, said


def test_port_range_and_network_host_warning(synth_session, tmp_path):
    s = synth_session
    res = _invoke("label", s.folder, "--calibration", s.calibration, "--skeleton", "rat",
                  "-o", tmp_path / "l.h5", "--port", "70000", "--no-browser")  # fmt: skip
    assert res.exit_code == 2 and "70000 is not in the range 0<=x<=65535" in res.output
    assert "Traceback" not in res.output and not (tmp_path / "l.h5").exists()
    for host in ("127.0.0.1", "::1", "localhost", "127.0.0.2"):
        assert network_warning(host) is None, host
    for host in ("0.0.0.0", "::", "192.168.1.20", "lab-pc.example"):
        msg = network_warning(host)
        assert msg is not None and "plain HTTP" in msg and "not encrypted" in msg, host
    with _label_server(s, tmp_path / "l.h5", "--host", "0.0.0.0") as (proc, _, lines):
        pass
    said = "".join(lines)
    assert "warning: --host 0.0.0.0 makes the page reachable from the network" in said, said
