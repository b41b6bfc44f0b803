"""Shared fixtures: a seeded RNG and a synthetic camera rig whose answers can be checked by hand."""

from __future__ import annotations

import importlib.util
import os
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path
from types import ModuleType

import numpy as np
import pytest

from freipose.geometry import CameraRig
from freipose.testing import make_circle_rig

REPO_ROOT = Path(__file__).resolve().parents[1]
SHARED_DATA = REPO_ROOT.parent / "shared" / "data"


@pytest.fixture(scope="module")
def bench(
    request: pytest.FixtureRequest, tmp_path_factory: pytest.TempPathFactory
) -> Iterator[ModuleType]:
    """The script ``benchmarks/<BENCHMARK>.py`` of the test module, loaded as a module.

    Its results go to a temporary folder (``FREIPOSE_RESULTS_DIR``), not the repository's.
    """
    name = request.module.BENCHMARK
    mp = pytest.MonkeyPatch()
    mp.syspath_prepend(str(REPO_ROOT / "benchmarks"))
    mp.setenv("FREIPOSE_RESULTS_DIR", str(tmp_path_factory.mktemp("results")))
    spec = importlib.util.spec_from_file_location(name, REPO_ROOT / "benchmarks" / f"{name}.py")
    if spec is None or spec.loader is None:
        raise FileNotFoundError(f"benchmarks/{name}.py")
    mod = importlib.util.module_from_spec(spec)
    sys.modules[name] = mod
    spec.loader.exec_module(mod)
    yield mod
    del sys.modules[name]
    mp.undo()


@pytest.fixture
def rng() -> np.random.Generator:
    """A seeded random generator (the same numbers in every test run)."""
    return np.random.default_rng(12345)


@pytest.fixture
def circle_rig() -> CameraRig:
    """Six 640x480 cameras, f = 800 px, on a 1 m circle at 0.6 m height looking at the origin."""
    return make_circle_rig()


@pytest.fixture
def distorted_rig() -> CameraRig:
    """The circle rig with a mild, different lens distortion per camera."""
    return make_circle_rig(distortion=True)


@pytest.fixture(scope="module")
def chromium() -> Iterator[object]:
    """A headless Chromium WebDriver (tests/browser.py); skips without Chromium or Selenium."""
    from browser import chromium_driver

    yield from chromium_driver()


@pytest.fixture
def shared_data() -> Path:
    """The read-only shared data folder; tests using it skip when it is absent."""
    if not SHARED_DATA.is_dir():
        pytest.skip(f"shared data folder not found at {SHARED_DATA} (only in the full workspace)")
    return SHARED_DATA


def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    """Skip tests marked ``gpu`` when no CUDA device is present."""
    import torch

    if torch.cuda.is_available():
        return
    skip = pytest.mark.skip(reason="needs a CUDA GPU; none is available on this machine")
    for item in items:
        if "gpu" in item.keywords:
            item.add_marker(skip)


_LOCK_HOLDER = """
import sys
from freipose.io.lock import output_lock
with output_lock(sys.argv[1], sys.argv[2]):
    print("held", flush=True)
    sys.stdin.read()
"""


class LockHolders:
    """Processes that each hold the output lock of one path until they are released."""

    def __init__(self) -> None:
        self.procs: list[subprocess.Popen] = []

    def hold(self, path: Path | str, what: str = "output") -> subprocess.Popen:
        """Start a process holding ``path``'s lock; returns once the lock is taken."""
        p = subprocess.Popen([sys.executable, "-c", _LOCK_HOLDER, str(path), what],
                             stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)  # fmt: skip
        self.procs.append(p)
        assert p.stdout is not None and p.stdout.readline().strip() == "held"
        return p

    def release(self, p: subprocess.Popen) -> int:
        """Let ``p`` leave its lock block and exit; returns its exit status."""
        if p.returncode is None:
            p.communicate("", timeout=30)
        return p.returncode


@pytest.fixture
def lock_holders() -> Iterator[LockHolders]:
    """Hold output locks from other processes (two runs on one output); released at the end."""
    holders = LockHolders()
    yield holders
    for p in holders.procs:
        holders.release(p)


@pytest.fixture(scope="session")
def own_data_run(tmp_path_factory: pytest.TempPathFactory) -> dict:
    """Every command of ``docs/own-data.md``, run once in a folder (``doc_pages.py``).

    Returns:
        ``folder`` (read-only for the tests: copy it to continue), ``outputs`` (by the
        commands' first two words) and ``ran`` (the number of commands).
    """
    pytest.importorskip("sleap_io")
    from click.testing import CliRunner
    from doc_pages import DOC, SUBSTITUTIONS, run_blocks, substituted

    text = substituted(DOC, SUBSTITUTIONS)
    folder = tmp_path_factory.mktemp("own_data")
    here = Path.cwd()
    os.chdir(folder)
    try:
        outputs, ran = run_blocks(text, CliRunner())
    finally:
        os.chdir(here)
    return {"folder": folder, "outputs": outputs, "ran": ran}
