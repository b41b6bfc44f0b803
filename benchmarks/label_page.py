"""Instant switch time of ``freipose label``: all views of the next instant shown.

Renders a synthetic session (``freipose synth``: 7 cameras at 640x480 by default) into a
temporary folder, starts the labeling server on it and switches N times to the next
instant, waiting ``--dwell`` seconds on each (the time a person spends labeling it, in
which the server prefetches the next instants). Prints the median and the maximum of:

* ``api``: the instant's JSON and every camera's JPEG fetched over HTTP, six requests at a
  time as a browser does;
* ``browser``: ``FP.load`` in headless Chromium until every image is decoded and every
  view drawn (skipped without ``chromium``/``chromedriver``).

``--dwell 0`` switches back to back (no time to prefetch). The instants are spread
evenly over the session, so every switch seeks in the videos.

Example::

    python benchmarks/label_page.py --switches 20 --dwell 1
"""

from __future__ import annotations

import argparse
import shutil
import statistics
import tempfile
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import httpx

from freipose.labelui.server import Running, background_server
from freipose.labelui.startup import open_store
from freipose.synth import SceneConfig, generate_session


def _api_switch(client: httpx.Client, pool: ThreadPoolExecutor, i: int, cams: list[str]) -> float:
    t0 = time.perf_counter()
    st = client.get(f"/api/instant/{i}")
    st.raise_for_status()
    futures = [pool.submit(client.get, f"/api/frame/{i}/{c}") for c in cams]
    for f in futures:
        f.result().raise_for_status()
    return (time.perf_counter() - t0) * 1000


def bench_api(running: Running, n: int, cams: list[str], dwell: float) -> list[float]:
    """Switch times (ms) over the HTTP API."""
    base = f"http://127.0.0.1:{running.port}"
    headers = {"X-FreiPose-Token": running.token}
    out = []
    with httpx.Client(base_url=base, headers=headers) as client, ThreadPoolExecutor(6) as pool:
        _api_switch(client, pool, 0, cams)
        for i in range(1, n + 1):
            time.sleep(dwell)
            out.append(_api_switch(client, pool, i, cams))
    return out


def bench_browser(running: Running, n: int, first: int, dwell: float) -> list[float] | None:
    """Switch times (ms) in headless Chromium, or None without a browser."""
    chromium, driver_path = shutil.which("chromium"), shutil.which("chromedriver")
    if chromium is None or driver_path is None:
        print("browser: skipped (chromium or chromedriver not installed)")
        return None
    from selenium import webdriver
    from selenium.webdriver.chrome.service import Service

    opts = webdriver.ChromeOptions()
    opts.binary_location = chromium
    for arg in ("--headless=new", "--no-sandbox", "--disable-gpu", "--window-size=1600,1000"):
        opts.add_argument(arg)
    d = webdriver.Chrome(service=Service(driver_path), options=opts)
    try:
        d.get(running.url)
        d.set_script_timeout(30)
        load = (
            "const done = arguments[arguments.length - 1];"
            "FP.load(arguments[0]).then(() => done(FP.S.lastSwitchMs));"
        )
        d.execute_async_script(load, first)
        out = []
        for i in range(first + 1, first + n + 1):
            time.sleep(dwell)
            out.append(float(d.execute_async_script(load, i)))
        return out
    finally:
        d.quit()


def _report(name: str, ms: list[float]) -> None:
    med = statistics.median(ms)
    print(f"{name}: median {med:.0f} ms, max {max(ms):.0f} ms over {len(ms)} switches")


def main() -> None:
    """Render the session, serve it, measure and print the switch times."""
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--cameras", type=int, default=7)
    ap.add_argument("--size", default="640x480", help="WIDTHxHEIGHT")
    ap.add_argument("--frames", type=int, default=200, help="frames of the session")
    ap.add_argument("--switches", type=int, default=15, help="switches per measurement")
    ap.add_argument("--dwell", type=float, default=1.0, help="seconds on each instant")
    ap.add_argument("--workdir", type=Path, help="keep the session here [a temporary folder]")
    args = ap.parse_args()
    w, h = (int(v) for v in args.size.lower().split("x"))
    tmp = None
    work = args.workdir
    if work is None:
        tmp = tempfile.TemporaryDirectory()
        work = Path(tmp.name)
    try:
        folder = work / "bench_session"
        t0 = time.perf_counter()
        cfg = SceneConfig(n_cameras=args.cameras, frames=args.frames, size=(w, h), seed=5)
        paths = generate_session(folder, cfg)
        print(f"synth: {args.cameras} cameras {w}x{h}, {args.frames} frames "
              f"({time.perf_counter() - t0:.0f} s)")  # fmt: skip
        per = 2 * args.switches + 3
        out = work / "labels.h5"
        store = open_store([folder], paths.calibration, "rat", out, per_session=per)
        cams = list(store.session(0).cameras)
        with background_server(store) as running:
            _report(
                f"api (dwell {args.dwell:g} s)", bench_api(running, args.switches, cams, args.dwell)
            )
            ms = bench_browser(running, args.switches, args.switches + 1, args.dwell)
            if ms is not None:
                _report(f"browser (dwell {args.dwell:g} s)", ms)
    finally:
        if tmp is not None:
            tmp.cleanup()


if __name__ == "__main__":
    main()
