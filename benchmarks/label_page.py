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
from _results import write_result

from freipose.io.labels import read_labels_h5
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


def _chrome(width: int = 1600, height: int = 1000):  # noqa: ANN202 - selenium's WebDriver
    """Headless Chromium, or None without ``chromium``/``chromedriver``."""
    chromium, driver_path = shutil.which("chromium"), shutil.which("chromedriver")
    if chromium is None or driver_path is None:
        return None
    from selenium import webdriver
    from selenium.webdriver.chrome.service import Service

    opts = webdriver.ChromeOptions()
    opts.binary_location = chromium
    for arg in ("--headless=new", "--no-sandbox", "--disable-gpu",
                f"--window-size={width},{height}", "--force-device-scale-factor=1"):  # fmt: skip
        opts.add_argument(arg)
    d = webdriver.Chrome(service=Service(driver_path), options=opts)
    d.set_script_timeout(30)
    return d


def _open(d, url: str) -> None:  # noqa: ANN001 - selenium's WebDriver
    """Open the page and wait until it shows its first instant."""
    d.get(url)
    end = time.monotonic() + 30
    while not d.execute_script("return document.body.dataset.instant !== undefined"):
        if time.monotonic() > end:
            raise RuntimeError("the labeling page did not load within 30 s")
        time.sleep(0.05)


LOAD = (
    "const done = arguments[arguments.length - 1];"
    "FP.load(arguments[0]).then(() => done(FP.S.lastSwitchMs));"
)


def bench_browser(running: Running, n: int, first: int, dwell: float) -> list[float] | None:
    """Switch times (ms) in headless Chromium, or None without a browser."""
    d = _chrome()
    if d is None:
        print("browser: skipped (chromium or chromedriver not installed)")
        return None
    try:
        _open(d, running.url)
        d.execute_async_script(LOAD, first)
        out = []
        for i in range(first + 1, first + n + 1):
            time.sleep(dwell)
            out.append(float(d.execute_async_script(LOAD, i)))
        return out
    finally:
        d.quit()


def screenshot(running: Running, truth_path: Path, frame: int, i: int, png: Path) -> None:
    """Label instant ``i`` from the truth (keypoints in two views, the Nose in all), screenshot."""
    truth = read_labels_h5(truth_path)
    labels: dict[str, dict[str, dict[str, object]]] = {}
    for v, cam in enumerate(truth.cameras):
        labels[cam] = {}
        for k, kp in enumerate(truth.keypoints):
            p = truth.points2d[frame, v, k]
            if truth.visible2d[frame, v, k] and (v < 2 or kp == "Nose"):
                labels[cam][kp] = {"state": "visible", "x": float(p[0]), "y": float(p[1])}
            elif v < 2:
                labels[cam][kp] = {"state": "occluded"}
    base = f"http://127.0.0.1:{running.port}"
    headers = {"X-FreiPose-Token": running.token}
    version = httpx.get(f"{base}/api/instant/{i}", headers=headers).json()["version"]
    r = httpx.post(f"{base}/api/instant/{i}", headers=headers,
                   json={"version": version, "labels": labels})  # fmt: skip
    r.raise_for_status()
    both = truth.visible2d[frame, :2].all(0)
    k = int(
        next(k for k in range(len(truth.keypoints)) if both[k] and truth.keypoints[k] != "Nose")
    )
    d = _chrome()
    if d is None:
        print("screenshot: skipped (chromium or chromedriver not installed)")
        return
    try:
        _open(d, running.url)
        d.execute_async_script(LOAD, i)
        d.execute_script("FP.S.kp = arguments[0]; FP.load(FP.S.idx)", k)
        time.sleep(1.0)
        zoom = (  # zoom every view 2.5x onto the animal (as the mouse wheel does)
            "for (const [cam, v] of Object.entries(FP.S.views)) {"
            "  const p = FP.shown(cam, 'Nose'); if (p) FP.setView(cam, v.s * 2.5, p.p[0], p.p[1]);"
            "}"
        )
        d.execute_script(zoom)
        time.sleep(0.3)
        d.save_screenshot(str(png))
        print(f"screenshot: {png}")
    finally:
        d.quit()


CLICK = """
const [cam, u, v] = arguments;
FP.setView(cam, 4, u, v);
const [x, y] = FP.imageToClient(cam, u, v);
return [Math.round(x), Math.round(y)];
"""


def clicks_per_keypoint(
    running: Running, truth_path: Path, frame: int, i: int
) -> dict[str, float] | None:
    """Label the Nose of instant ``i`` in every view with two clicks and Enter, as a user would.

    Prints the number of actions and how far the accepted projections lie from the true
    projections of the synthetic truth.

    Returns:
        The actions, views labeled and projection errors (px), or None without a browser.
    """
    import numpy as np
    from selenium.webdriver.common.actions.action_builder import ActionBuilder
    from selenium.webdriver.common.keys import Keys

    truth = read_labels_h5(truth_path)
    k = truth.keypoints.index("Nose")
    views = [v for v in range(len(truth.cameras)) if truth.visible2d[frame, v, k]]
    d = _chrome()
    if d is None or len(views) < 3:
        print("clicks: skipped (no browser, or the Nose is seen in fewer than 3 views)")
        return None
    try:
        _open(d, running.url)
        d.execute_async_script(LOAD, i)
        d.execute_script("FP.S.kp = arguments[0]; FP.load(FP.S.idx)", k)
        time.sleep(0.5)
        actions = 0
        for v in views[:2]:
            x, y = d.execute_script(
                CLICK, truth.cameras[v], *map(float, truth.points2d[frame, v, k])
            )
            ab = ActionBuilder(d)
            ab.pointer_action.move_to_location(x, y).click()
            ab.perform()
            actions += 1
            time.sleep(0.5)
        d.find_element("tag name", "body").send_keys(Keys.ENTER)
        actions += 1
        time.sleep(1.0)
        labels = d.execute_script("return FP.S.cur.labels")
    finally:
        d.quit()
    errs = []
    for v in views[2:]:
        lab = labels[truth.cameras[v]].get("Nose")
        if lab is not None and lab["state"] == "visible":
            errs.append(
                float(np.hypot(*(np.array([lab["x"], lab["y"]]) - truth.points2d[frame, v, k])))
            )
    worst, med = max(errs), float(np.median(errs))
    print(f"clicks: the Nose labeled in {2 + len(errs)} of the {len(views)} views that see it "
          f"with {actions} actions (2 clicks at its true positions, Enter); the {len(errs)} "
          f"accepted projections lie {worst:.2f} px at most (median {med:.2f} px) from the "
          "true projections")  # fmt: skip
    return {"actions": actions, "views_labeled": 2 + len(errs), "views_seeing": len(views),
            "projection_error_max_px": worst, "projection_error_median_px": med}  # fmt: skip


def _report(name: str, ms: list[float]) -> dict[str, float]:
    med = statistics.median(ms)
    print(f"{name}: median {med:.0f} ms, max {max(ms):.0f} ms over {len(ms)} switches")
    return {"median_ms": med, "max_ms": max(ms), "switches": len(ms)}


def main() -> None:
    """Render the session, serve it, measure and print the switch times."""
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--cameras", type=int, default=7)
    ap.add_argument("--size", default="640x480", help="WIDTHxHEIGHT")
    ap.add_argument("--frames", type=int, default=200, help="frames of the session")
    ap.add_argument("--switches", type=int, default=15, help="switches per measurement")
    ap.add_argument("--dwell", type=float, default=1.0, help="seconds on each instant")
    ap.add_argument("--workdir", type=Path, help="keep the session here [a temporary folder]")
    ap.add_argument("--screenshot", type=Path, help="also save a screenshot of a labeled instant")
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
        figures: dict[str, object] = {}
        with background_server(store) as running:
            api = bench_api(running, args.switches, cams, args.dwell)
            figures["api switch"] = _report(f"api (dwell {args.dwell:g} s)", api)
            ms = bench_browser(running, args.switches, args.switches + 1, args.dwell)
            if ms is not None:
                figures["browser switch"] = _report(f"browser (dwell {args.dwell:g} s)", ms)
            clicks = clicks_per_keypoint(running, paths.labels, store.instants[0].frame, 0)
            if clicks is not None:
                figures["clicks"] = clicks
            if args.screenshot is not None:
                last = len(store) - 1
                screenshot(running, paths.labels, store.instants[last].frame, last, args.screenshot)
        settings = {k: getattr(args, k) for k in ("cameras", "size", "frames", "switches", "dwell")}
        write_result("label_page", figures, extra={"seed": 5, **settings})
    finally:
        if tmp is not None:
            tmp.cleanup()


if __name__ == "__main__":
    main()
