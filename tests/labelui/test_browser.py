"""The labeling page in a real headless Chromium (Selenium) on a session with known truth.

Skips, saying why, where ``chromium`` or ``chromedriver`` is not installed. Screenshots go
to the test's temporary folder and, where ``FREIPOSE_TEST_ARTEFACTS`` is set, there too.
"""

from __future__ import annotations

import os
import shutil
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import httpx
import numpy as np
import pytest

from freipose.geometry.projection import pixel_to_ray, project
from freipose.geometry.triangulation import triangulate_weighted
from freipose.io.labels import read_labels_h5
from freipose.labelui.server import Running, background_server
from freipose.labelui.startup import open_store
from freipose.labelui.store import LabelStore

webdriver = pytest.importorskip("selenium.webdriver")
from selenium.webdriver.common.action_chains import ActionChains, ScrollOrigin  # noqa: E402
from selenium.webdriver.common.actions.action_builder import ActionBuilder  # noqa: E402
from selenium.webdriver.common.by import By  # noqa: E402
from selenium.webdriver.common.keys import Keys  # noqa: E402

CHROMIUM = shutil.which("chromium") or shutil.which("chromium-browser")
DRIVER = shutil.which("chromedriver")


@pytest.fixture
def driver() -> Iterator[Any]:
    if CHROMIUM is None or DRIVER is None:
        pytest.skip(
            "browser tests need chromium and chromedriver (Debian: chromium, chromium-driver)"
        )
    from selenium.webdriver.chrome.service import Service

    opts = webdriver.ChromeOptions()
    opts.binary_location = CHROMIUM
    for arg in ("--headless=new", "--no-sandbox", "--disable-gpu", "--disable-dev-shm-usage",
                "--window-size=1400,900", "--force-device-scale-factor=1"):  # fmt: skip
        opts.add_argument(arg)
    d = webdriver.Chrome(service=Service(DRIVER), options=opts)
    try:
        yield d
    finally:
        d.quit()


def _wait(fn: Callable[[], Any], timeout: float = 10.0) -> Any:
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        value = fn()
        if value:
            return value
        time.sleep(0.05)
    raise AssertionError("timed out waiting for the page")


def _shot(driver: Any, folder: Path, name: str) -> Path:
    path = folder / f"{name}.png"
    driver.save_screenshot(str(path))
    art = os.environ.get("FREIPOSE_TEST_ARTEFACTS")
    if art:
        Path(art).mkdir(parents=True, exist_ok=True)
        shutil.copy(path, Path(art) / path.name)
    return path


def _open(driver: Any, running: Running) -> None:
    driver.get(running.url)
    _wait(lambda: driver.execute_script("return document.body.dataset.instant !== undefined"))


def _pointer(driver: Any, path: list[tuple[int, int]], hold: bool = False) -> None:
    """Mouse: move to path[0], press (and hold along the rest of the path), release."""
    ab = ActionBuilder(driver)
    p = ab.pointer_action
    p.move_to_location(*path[0])
    p.pointer_down()
    for x, y in path[1:]:
        p.move_to_location(x, y)
    p.pointer_up()
    ab.perform()


def _click_image(driver: Any, cam: str, uv: np.ndarray, zoom: float = 4.0) -> None:
    """Zoom the view of ``cam`` on pixel ``uv`` and click there with the mouse."""
    u, v = float(uv[0]), float(uv[1])
    driver.execute_script("FP.setView(arguments[0], arguments[1], arguments[2], arguments[3])",
                          cam, zoom, u, v)  # fmt: skip
    x, y = driver.execute_script("return FP.imageToClient(arguments[0], arguments[1], "
                                 "arguments[2])", cam, u, v)  # fmt: skip
    _pointer(driver, [(round(x), round(y))])


def _state(driver: Any) -> dict[str, Any]:
    return driver.execute_script("return FP.S.cur")


def _select_keypoint(driver: Any, k: int) -> None:
    driver.find_element(By.CSS_SELECTOR, f'.kp[data-k="{k}"]').click()


def _visible_everywhere(synth_session, frame: int) -> list[int]:
    t = synth_session.truth
    vis = t.visible2d[frame]  # (V, K)
    return [k for k in range(len(t.keypoints)) if vis[:, k].all()]


def test_label_two_views_projected_third_drag_reload(driver, store: LabelStore, synth_session,
                                                    tmp_path):  # fmt: skip
    truth = synth_session.truth
    frame = store.instants[0].frame
    k1, k2 = _visible_everywhere(synth_session, frame)[:2]
    kp1, kp2 = truth.keypoints[k1], truth.keypoints[k2]
    t2d = truth.points2d[frame]  # (V, K, 2)
    with background_server(store) as running:
        _open(driver, running)
        sizes = driver.execute_script(
            "return Object.values(FP.S.views).map((v) => [v.img.naturalWidth, v.img.naturalHeight])"
        )
        assert sizes == [[320, 256]] * 3  # every view's frame arrived and decoded
        _select_keypoint(driver, k1)
        _click_image(driver, "cam0", t2d[0, k1])
        _wait(lambda: _state(driver)["version"] == 1)
        # press in cam1 and drag: cam2 shows the projection live, before any save
        u, v = (float(c) for c in t2d[1, k1])
        driver.execute_script("FP.setView('cam1', 4, arguments[0], arguments[1])", u, v)
        x, y = (round(c) for c in driver.execute_script(
            "return FP.imageToClient('cam1', arguments[0], arguments[1])", u, v))  # fmt: skip
        ab = ActionBuilder(driver)
        ab.pointer_action.move_to_location(x, y).pointer_down().move_to_location(x + 8, y)
        ab.perform()
        live = driver.execute_script("return FP.shown('cam2', arguments[0])", kp1)
        assert live["kind"] == "projected" and _state(driver)["version"] == 1
        rig = store.session(0).rig
        obs = np.stack([t2d[0, k1], t2d[1, k1] + [2.0, 0.0], [np.nan, np.nan]])
        X = triangulate_weighted(obs, np.array([1.0, 1.0, 0.0]), rig)
        assert np.linalg.norm(np.array(live["p"]) - project(X, rig["cam2"])) < 0.3  # px
        ab = ActionBuilder(driver)
        ab.pointer_action.move_to_location(x, y).pointer_up()
        ab.perform()
        st = _wait(lambda: (s := _state(driver))["points3d"].get(kp1) and s)
        proj = np.array(st["projected"]["cam2"][kp1])
        assert np.linalg.norm(proj - t2d[2, k1]) < 1.0  # px, against the true projection
        assert (
            driver.execute_script("return FP.shown('cam2', arguments[0]).kind", kp1) == "projected"
        )
        _shot(driver, tmp_path, "label_projected")
        # drag the hollow projected marker: it becomes a label where it is dropped
        driver.execute_script("FP.setView('cam2', 4, arguments[0], arguments[1])", *proj.tolist())
        x, y = driver.execute_script("return FP.imageToClient('cam2', arguments[0], arguments[1])",
                                     *proj.tolist())  # fmt: skip
        x, y = round(x), round(y)
        before = st["version"]
        _pointer(driver, [(x, y), (x + 4, y + 2), (x + 8, y + 4)])
        st = _wait(lambda: (s := _state(driver))["version"] > before and s)
        lab = st["labels"]["cam2"][kp1]
        assert lab["state"] == "visible"
        np.testing.assert_allclose([lab["x"], lab["y"]], proj + [2.0, 1.0], atol=0.3)
        # a second keypoint: two clicks, Enter accepts the projection into the third view
        _select_keypoint(driver, k2)
        _click_image(driver, "cam1", t2d[1, k2])
        _click_image(driver, "cam2", t2d[2, k2])
        _wait(lambda: _state(driver)["points3d"].get(kp2))
        v = _state(driver)["version"]
        driver.find_element(By.TAG_NAME, "body").send_keys(Keys.ENTER)
        st = _wait(lambda: (s := _state(driver))["version"] > v and s)
        acc = st["labels"]["cam0"][kp2]
        assert np.linalg.norm([acc["x"] - t2d[0, k2, 0], acc["y"] - t2d[0, k2, 1]]) < 1.0
        driver.execute_script("Object.values(FP.S.views).forEach((v) => { v.fitted = false; });"
                              "FP.load(FP.S.idx)")  # fmt: skip
        time.sleep(0.5)
        _shot(driver, tmp_path, "label_page")
        # the saved file
        ls = read_labels_h5(store.output)
        assert list(ls.frame_index) == [frame]
        np.testing.assert_allclose(ls.points2d[0, 0, k1], t2d[0, k1], atol=0.3)
        np.testing.assert_allclose(ls.points2d[0, 1, k1], t2d[1, k1], atol=0.3)
        np.testing.assert_allclose(ls.points2d[0, 2, k1], proj + [2.0, 1.0], atol=0.3)
        assert ls.visible2d[0, :, k1].all() and ls.visible2d[0, :, k2].all()
        X = triangulate_weighted(ls.points2d[0, :, k1], np.ones(3), store.session(0).rig)
        np.testing.assert_allclose(ls.points3d[0, k1], X, atol=1e-6)  # from the saved labels
        assert np.linalg.norm(X - truth.points3d[frame, k1]) < 10.0  # mm (cam2 moved 2 px)
        # reload: the page opens the first unlabeled instant; Left goes back to ours
        driver.refresh()
        _wait(lambda: driver.execute_script("return document.body.dataset.instant === '1'"))
        driver.find_element(By.TAG_NAME, "body").send_keys(Keys.ARROW_LEFT)
        _wait(lambda: driver.execute_script("return document.body.dataset.instant === '0'"))
        again = driver.execute_script("return FP.S.labels")
        assert again["cam2"][kp1] == lab and again["cam0"][kp2] == acc


def test_epipolar_curve_and_projection_in_js_match_python(driver, store, synth_session):
    rig = store.session(0).rig
    with background_server(store) as running:
        _open(driver, running)
        uv = np.array([150.3, 120.7])
        dists = [200.0, 500.0, 900.0, 1400.0]
        js = driver.execute_script(
            "const c = FP.S.cfg.cameras; return FPGeom.epipolar(c['rat1/cam0'], arguments[0], "
            "arguments[1], c['rat1/cam2'], arguments[2])",
            float(uv[0]),
            float(uv[1]),
            dists,
        )
        o, d = pixel_to_ray(uv, rig["cam0"])
        want = project(o + np.array(dists)[:, None] * d, rig["cam2"])
        np.testing.assert_allclose(np.array(js, dtype=float), want, atol=1e-6)
        und = driver.execute_script("return FPGeom.undistort(0.31, -0.22, arguments[0])",
                                    rig["cam1"].dist.tolist())  # fmt: skip
        from freipose.geometry.distortion import undistort_normalized

        t = synth_session.truth
        js3d = driver.execute_script(
            "const c = FP.S.cfg.cameras;"
            "return FPGeom.triangulate([c['rat1/cam0'], c['rat1/cam2']], arguments[0])",
            t.points2d[5, [0, 2], 10].tolist(),
        )
        np.testing.assert_allclose(js3d, t.points3d[5, 10], atol=1e-6)  # exact projections
        want_und = undistort_normalized(np.array([0.31, -0.22]), rig["cam1"].dist)
        np.testing.assert_allclose(und, want_und, atol=1e-12)
        assert rig["cam1"].has_distortion


def test_conflict_from_another_tab_is_shown_and_reloaded(driver, store, synth_session, tmp_path):
    truth = synth_session.truth
    frame = store.instants[0].frame
    k = _visible_everywhere(synth_session, frame)[0]
    with background_server(store) as running:
        _open(driver, running)
        # another client saves the same instant first
        body = {"version": 0, "labels": {"cam1": {"Tail": {"state": "occluded"}}}}
        r = httpx.post(f"http://127.0.0.1:{running.port}/api/instant/0", json=body,
                       headers={"X-FreiPose-Token": running.token})  # fmt: skip
        assert r.status_code == 200
        _select_keypoint(driver, k)
        _click_image(driver, "cam0", truth.points2d[frame, 0, k])
        _wait(lambda: driver.execute_script("return FP.S.conflicts") == 1)
        banner = driver.find_element(By.ID, "banner")
        assert banner.is_displayed() and "another tab" in banner.text
        labels = driver.execute_script("return FP.S.labels")
        assert labels["cam1"] == {"Tail": {"state": "occluded"}} and labels["cam0"] == {}
        _shot(driver, tmp_path, "label_conflict")


def test_keys_mark_occluded_and_undo(driver, store, synth_session):
    truth = synth_session.truth
    frame = store.instants[0].frame
    k = _visible_everywhere(synth_session, frame)[0]
    kp = truth.keypoints[k]
    with background_server(store) as running:
        _open(driver, running)
        body = driver.find_element(By.TAG_NAME, "body")
        _select_keypoint(driver, k)
        _click_image(driver, "cam1", truth.points2d[frame, 1, k])  # cam1 becomes the active view
        _wait(lambda: _state(driver)["version"] == 1)
        assert _state(driver)["labels"]["cam1"][kp]["state"] == "visible"
        body.send_keys("o")
        _wait(lambda: _state(driver)["version"] == 2)
        assert _state(driver)["labels"]["cam1"][kp] == {"state": "occluded"}
        body.send_keys("x")
        _wait(lambda: _state(driver)["version"] == 3)
        assert _state(driver)["labels"]["cam1"][kp] == {"state": "notinview"}
        body.send_keys("z")
        body.send_keys("z")
        _wait(lambda: _state(driver)["version"] == 5)
        assert _state(driver)["labels"]["cam1"][kp]["state"] == "visible"  # two undos back
        body.send_keys(Keys.DELETE)
        _wait(lambda: _state(driver)["version"] == 6)
        assert kp not in _state(driver)["labels"]["cam1"]
        # the wheel zooms, Shift+drag pans (and neither labels anything)
        view = "return [FP.S.views.cam2.s, FP.S.views.cam2.tx, FP.S.views.cam2.ty]"
        s0, tx0, _ = driver.execute_script(view)
        canvas = driver.find_element(By.CSS_SELECTOR, '.view[data-camera="cam2"] canvas')
        ActionChains(driver).scroll_from_origin(
            ScrollOrigin.from_element(canvas), 0, -300
        ).perform()
        s1, tx1, ty1 = _wait(lambda: (v := driver.execute_script(view))[0] != s0 and v)
        assert s1 > 1.3 * s0
        ActionChains(driver).move_to_element(canvas).key_down(
            Keys.SHIFT
        ).click_and_hold().move_by_offset(40, 25).release().key_up(Keys.SHIFT).perform()
        _, tx2, ty2 = driver.execute_script(view)
        assert (tx2 - tx1, ty2 - ty1) == pytest.approx((40, 25), abs=1)
        assert _state(driver)["version"] == 6 and _state(driver)["labels"]["cam2"] == {}
        # an edit and at once the next instant: the edit is saved to its own instant
        _click_image(driver, "cam2", truth.points2d[frame, 2, k])
        body.send_keys(Keys.ARROW_RIGHT)
        _wait(lambda: driver.execute_script("return document.body.dataset.instant === '1'"))
        assert store.state(0)["labels"]["cam2"][kp]["state"] == "visible"
        assert store.state(1)["version"] == 0


def test_predicted_markers_accepted_and_least_confident_button(driver, synth_session, poses_dir,
                                                                 tmp_path):  # fmt: skip
    s = synth_session
    store = open_store([s.folder], s.calibration, "rat", tmp_path / "l.h5", poses_dir=poses_dir,
                       per_session=3)  # frames 0, 6 (confidence 0.1) and 11  # fmt: skip
    with background_server(store) as running:
        _open(driver, running)
        assert driver.execute_script("return FP.S.idx") == 0
        driver.find_element(By.ID, "least").click()
        _wait(lambda: driver.execute_script("return document.body.dataset.instant === '1'"))
        k = s.truth.keypoints.index("Nose")
        _select_keypoint(driver, k)
        assert driver.execute_script("return FP.shown('cam0', 'Nose').kind") == "predicted"
        assert not any(_state(driver)["labels"].values())  # predictions are not labels
        driver.find_element(By.ID, "accept").click()  # accept the predicted Nose
        st = _wait(lambda: (x := _state(driver))["version"] == 1 and x)
        want = store.session(1).rig.project(s.truth.points3d[6, k][None] + 2.0)[:, 0]  # (V, 2)
        for v, cam in enumerate(st["cameras"]):
            lab = st["labels"][cam]["Nose"]
            np.testing.assert_allclose([lab["x"], lab["y"]], want[v], atol=2e-3)
        assert len(read_labels_h5(tmp_path / "l.h5")) == 1


def test_several_animals_selector_and_the_others_drawn(driver, pair, tmp_path):
    """Two rats: the animal buttons switch between the animals of a frame (and A does), a
    label goes to the selected animal, and the other animal's labels are drawn."""
    folder, calib, truth = pair
    store = open_store([folder], calib, "rat", tmp_path / "labels.h5", per_session=2,
                       animals=("animal0", "animal1"))  # fmt: skip
    frame = store.instants[0].frame
    rows = {a: int(np.flatnonzero((truth.frame_index == frame) & (truth.individual == a))[0])
            for a in ("animal0", "animal1")}  # fmt: skip
    k = next(
        k
        for k in range(len(truth.keypoints))
        if truth.visible2d[rows["animal0"], 0, k] and truth.visible2d[rows["animal1"], 0, k]
    )
    kp = truth.keypoints[k]
    with background_server(store) as running:
        _open(driver, running)
        buttons = driver.find_elements(By.CSS_SELECTOR, "#animals button.animal")
        assert [b.get_attribute("data-animal") for b in buttons] == ["animal0", "animal1"]
        assert "animal0" in driver.find_element(By.ID, "where").text
        _select_keypoint(driver, k)
        _click_image(driver, "cam0", truth.points2d[rows["animal0"], 0, k])
        _wait(lambda: _state(driver)["version"] == 1)
        # A: the other animal of the same frame, with the first one's label drawn
        driver.find_element(By.TAG_NAME, "body").send_keys("a")
        _wait(lambda: driver.execute_script("return document.body.dataset.instant === '1'"))
        st = _state(driver)
        assert st["individual"] == "animal1" and st["labels"]["cam0"] == {}
        drawn = st["others"]["animal0"]["cam0"][kp]
        np.testing.assert_allclose(drawn, truth.points2d[rows["animal0"], 0, k], atol=0.3)
        _select_keypoint(driver, k)
        _click_image(driver, "cam0", truth.points2d[rows["animal1"], 0, k])
        _wait(lambda: _state(driver)["version"] == 1)
        driver.execute_script("Object.values(FP.S.views).forEach((v) => { v.fitted = false; });"
                              "FP.load(FP.S.idx)")  # fmt: skip
        time.sleep(0.5)
        labeled = [b.text for b in driver.find_elements(By.CSS_SELECTOR, "#animals button")]
        assert labeled == ["animal0 \u2713", "animal1 \u2713"]
        _shot(driver, tmp_path, "label_animals")
        # the button goes back to the first animal
        driver.find_element(By.CSS_SELECTOR, '#animals button[data-animal="animal0"]').click()
        _wait(lambda: driver.execute_script("return document.body.dataset.instant === '0'"))
    ls = read_labels_h5(store.output)
    assert list(ls.individual) == ["animal0", "animal1"]
    for r, a in enumerate(("animal0", "animal1")):
        np.testing.assert_allclose(ls.points2d[r, 0, k], truth.points2d[rows[a], 0, k], atol=0.3)
