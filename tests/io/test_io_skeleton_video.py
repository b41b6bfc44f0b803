"""Skeleton definitions and video/image-folder frame sources and writers."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
import tomli_w

from freipose.io.video import (
    FrameSource,
    MediaError,
    VideoWriter,
    find_camera_videos,
    find_video,
    frame_range,
    list_images,
)
from freipose.skeleton import BUILTIN_SKELETONS, load_skeleton, skeleton_from_dict

RAT = [
    "Ear Right", "Eye Right", "Paw Front Right", "Paw Back Right Ankle", "Paw Back Right Tip",
    "Ear Left", "Eye Left", "Paw Front Left", "Paw Back Left Ankle", "Paw Back Left Tip",
    "Nose", "Tail",
]  # fmt: skip


def test_shipped_skeletons():
    rat = load_skeleton("rat")
    assert list(rat.keypoints) == RAT
    assert load_skeleton("paw").num_keypoints == 15
    assert load_skeleton("mouse").num_keypoints == 12
    for name in BUILTIN_SKELETONS:
        s = load_skeleton(name)
        assert skeleton_from_dict(s.to_dict()).to_dict() == s.to_dict()
    # A limb end may be the midpoint of two keypoints: (Ear Right + Ear Left) / 2 -> Tail.
    ears_to_tail = ((0, 5), (11,))
    assert ears_to_tail in rat.limbs
    poses = np.zeros((1, 12, 3))
    poses[0, 0] = (10, 0, 0)
    poses[0, 5] = (-10, 0, 0)
    poses[0, 11] = (0, 30, 0)
    lengths = rat.limb_lengths(poses)
    assert lengths.shape == (1, len(rat.limbs))
    assert lengths[0, rat.limbs.index(ears_to_tail)] == pytest.approx(30.0)
    perm = rat.mirror_permutation()
    assert [rat.keypoints[i] for i in perm][:2] == ["Ear Left", "Eye Left"]
    assert np.array_equal(perm[perm], np.arange(12))
    assert rat.index("Tail") == 11
    with pytest.raises(KeyError, match="no keypoint 'Wing'"):
        rat.index("Wing")
    assert set(rat.angles) >= {"body_elevation", "head_roll"}
    assert rat.frame["origin"] == (0, 5)


def test_user_skeleton_file_and_errors(tmp_path):
    p = tmp_path / "fly.toml"
    p.write_text(tomli_w.dumps({
        "name": "fly", "keypoints": ["head", "thorax", "abdomen"],
        "limbs": [["head", "thorax"], [["head", "abdomen"], "thorax"]],
        "angles": {"tilt": [["g"], ["abdomen", "head"]]},
    }))  # fmt: skip
    fly = load_skeleton(p)
    assert fly.limbs == (((0,), (1,)), ((0, 2), (1,)))
    assert fly.angles["tilt"] == (("g",), ((2,), (0,)))
    with pytest.raises(FileNotFoundError, match="neither a shipped skeleton"):
        load_skeleton("dragon")
    p.write_text("name = [")
    with pytest.raises(ValueError, match="not valid TOML"):
        load_skeleton(p)
    with pytest.raises(ValueError, match="missing required field 'keypoints'"):
        skeleton_from_dict({"name": "x"})
    with pytest.raises(ValueError, match="unknown keypoint 'wing'"):
        skeleton_from_dict({"name": "x", "keypoints": ["a", "b"], "limbs": [["a", "wing"]]})
    with pytest.raises(ValueError, match="two ends"):
        skeleton_from_dict({"name": "x", "keypoints": ["a", "b"], "limbs": [["a", "b", "a"]]})
    with pytest.raises(ValueError, match="repeated keypoint names"):
        skeleton_from_dict({"name": "x", "keypoints": ["a", "a"]})
    with pytest.raises(ValueError, match="keypoints must be a list"):
        skeleton_from_dict({"name": "x", "keypoints": "abc"})
    with pytest.raises(ValueError, match="two vectors"):
        skeleton_from_dict({"name": "x", "keypoints": ["a", "b"], "angles": {"t": [["g"]] * 3}})
    with pytest.raises(ValueError, match="symmetry entry must be two names"):
        skeleton_from_dict({"name": "x", "keypoints": ["a", "b"], "symmetry": [["a", "b", "a"]]})
    with pytest.raises(ValueError, match="angle 'bad'"):
        skeleton_from_dict(
            {"name": "x", "keypoints": ["a", "b"], "angles": {"bad": [["g"], ["a"]]}}
        )


def _frames(n: int, w: int = 32, h: int = 24) -> list[np.ndarray]:
    out = []
    for i in range(n):
        f = np.zeros((h, w, 3), np.uint8)
        f[..., 1] = 20 * i  # a different flat grey per frame
        f[2:6, 2 + i : 6 + i] = 255
        out.append(f)
    return out


def test_video_round_trip_lossless_mkv(tmp_path):
    frames = _frames(8)
    p = tmp_path / "cam0.mkv"
    with VideoWriter(p, 25.0, (32, 24)) as w:
        for f in frames:
            w.write(f)
        assert not p.exists()  # only under its name once complete
    assert p.exists() and w.frames == 8
    with FrameSource(p, cache_size=2) as src:
        assert (src.num_frames, src.size, src.name) == (8, (32, 24), "cam0")
        assert src.fps == pytest.approx(25.0)
        for i in (0, 5, 2, 7, 7, 3):  # random access, backwards and forwards
            np.testing.assert_array_equal(src.read(i), frames[i])
        np.testing.assert_array_equal(src[1], frames[1])
        with pytest.raises(IndexError, match="outside 0..7"):
            src.read(8)


def test_video_writer_errors_and_abort(tmp_path):
    with pytest.raises(MediaError, match="cannot write '.gif'"):
        VideoWriter(tmp_path / "x.gif", 10, (32, 24))
    w = VideoWriter(tmp_path / "y.avi", 10, (32, 24))
    with pytest.raises(ValueError, match="uint8 of size"):
        w.write(np.zeros((10, 10, 3), np.uint8))
    w.write(np.zeros((24, 32), np.uint8))  # grey frames are accepted
    w.abort()
    assert list(tmp_path.iterdir()) == []
    with pytest.raises(RuntimeError), VideoWriter(tmp_path / "z.mp4", 10, (32, 24)) as w2:
        w2.write(np.zeros((24, 32, 3), np.uint8))
        raise RuntimeError("interrupted")
    assert list(tmp_path.iterdir()) == []  # an interrupted write leaves nothing


def test_frame_source_errors(tmp_path):
    with pytest.raises(MediaError, match="no such video file or image folder"):
        FrameSource(tmp_path / "none.mp4")
    bad = tmp_path / "bad.mp4"
    bad.write_bytes(b"\x00" * 1000)
    with pytest.raises(MediaError, match="cannot"):
        FrameSource(bad)
    empty = tmp_path / "empty"
    empty.mkdir()
    with pytest.raises(MediaError, match="holds no images"):
        FrameSource(empty)
    (empty / "0.png").write_bytes(b"not a png")
    with pytest.raises(MediaError, match="cannot be read as an image"):
        FrameSource(empty)


def test_image_folder_in_numeric_order(tmp_path):
    frames = _frames(12)
    folder = tmp_path / "cam3"
    folder.mkdir()
    for i, f in enumerate(frames):
        cv2.imwrite(str(folder / f"{i}.png"), f)  # 0.png .. 11.png: 10 sorts after 9
    src = FrameSource(folder)
    assert (src.num_frames, src.size, src.name) == (12, (32, 24), "cam3")
    for i in (0, 2, 9, 10, 11):
        np.testing.assert_array_equal(src.read(i), frames[i])


def test_find_camera_videos(tmp_path):
    for name in ("cam10", "cam2", ".hidden"):
        (tmp_path / f"{name}.mp4").write_bytes(b"")
    (tmp_path / "notes.txt").write_text("x")
    vids = find_camera_videos(tmp_path)
    assert sorted(vids) == ["cam10", "cam2"]
    empty = tmp_path / "e"
    empty.mkdir()
    with pytest.raises(MediaError, match="no videos found"):
        find_camera_videos(empty)
    with pytest.raises(MediaError, match="not a folder"):
        find_camera_videos(tmp_path / "notes.txt")


def test_video_helpers_find_list_and_frame_ranges(tmp_path):
    a, b = tmp_path / "a", tmp_path / "b"
    a.mkdir()
    b.mkdir()
    (b / "cam0.avi").write_bytes(b"x")
    assert find_video("cam0", (a, b)) == b / "cam0.avi"
    (a / "cam0.mp4").write_bytes(b"x")
    assert find_video("cam0", (a, b)) == a / "cam0.mp4"  # earlier folder first
    assert find_video("cam1", (a, b)) is None
    for name in ("img10.png", "img2.png", ".hidden.png", "notes.txt"):
        (a / name).write_bytes(b"x")
    assert [p.name for p in list_images(a)] == ["img2.png", "img10.png"]
    assert frame_range(None, 5) == range(5) and frame_range("", 5) == range(5)
    assert frame_range("-2:", 10) == range(8, 10) and frame_range(":3", 10) == range(3)
    assert frame_range("5:99", 10) == range(5, 10)  # clipped (with a warning)
    with pytest.raises(ValueError, match="START:STOP"):
        frame_range("5", 10)
    with pytest.raises(ValueError, match="selects no frames"):
        frame_range("7:3", 10)
