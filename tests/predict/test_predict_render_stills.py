"""Still images of predicted poses: every camera cropped to the animal, full-view inset, legend."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
from predict_helpers import BlobEstimator, make_session

from freipose.io.poses import read_poses_h5
from freipose.io.session import discover_sessions
from freipose.predict.render import (
    RenderError,
    confidence_color,
    confidence_legend,
    draw_label,
    render_stills,
    still_tile,
)
from freipose.predict.run import predict_session


def test_still_tile_crops_to_the_keypoints_and_insets_the_view():
    img = np.full((200, 300, 3), 50, np.uint8)
    uv = np.array([[140.0, 90.0], [160.0, 110.0]])
    tile = still_tile(img, uv, np.array([1.0, 1.0]), [((0,), (1,))], "cam0", tile=120)
    assert tile.shape == (120, 120, 3)
    # the crop is square around the points (extent 20 px, margins 35 %: 48 px minimum),
    # scaled 2.5x: the first point lands at (140 - 126) * 2.5 + 0.75 ~ 36 px, drawn green
    side = 48
    x0, y0 = 150 - side // 2, 100 - side // 2
    s = 120 / side
    x, y = (np.array([140.0, 90.0]) - (x0, y0)) * s + (s - 1) / 2
    px = tile[int(round(y)), int(round(x))].astype(int)
    assert tuple(px) == confidence_color(1.0)
    # the inset (a third of the tile, top right) is framed in white
    assert (tile[1, 120 - 40 - 3 : 118] == 255).all()


def test_confidence_legend_runs_from_red_to_green():
    leg = confidence_legend(400)
    assert leg.shape == (34, 400, 3)
    assert tuple(leg[10, 110]) == confidence_color(0.0)
    assert tuple(leg[10, 369]) == confidence_color(1.0)


def test_render_stills(tmp_path):
    folder = tmp_path / "rec"
    make_session(folder, 6, n_cams=3)
    (s,) = discover_sessions([folder])
    poses = predict_session(s, BlobEstimator(), tmp_path, batch_size=4, progress=False).path
    d = read_poses_h5(poses)
    videos = [folder / f"{n}.mp4" for n in d.calibration.names]
    out = render_stills(videos, d.calibration, d, [1, 4], [tmp_path / "a.png", tmp_path / "b.png"],
                        tile=100)  # fmt: skip
    assert [p.name for p in out] == ["a.png", "b.png"]
    img = cv2.imread(str(out[0]))
    assert img.shape == (100 + 34, 3 * 100, 3)  # one row of three tiles and the legend
    with pytest.raises(RenderError, match="frame 9"):
        render_stills(videos, d.calibration, d, [9], [tmp_path / "c.png"])
    assert not (tmp_path / "c.png").exists()


def test_labels_are_white_on_a_dark_box():
    img = np.full((40, 200, 3), 200, np.uint8)
    draw_label(img, "cam0  frame 13", (8, 22), 0.6)
    box = img[8:26, 4:150]
    assert (box == 70).mean() > 0.5  # the background dimmed to 35 %
    assert (box == 255).all(-1).any()  # white text
    assert (img[:, 190:] == 200).all()  # nothing drawn beyond the text
