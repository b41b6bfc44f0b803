"""Overlay videos of predicted poses, tiled in a grid.

Every camera view shows the projected skeleton; a 3D skeleton panel shows the pose.

Keypoints and limbs are coloured by confidence (red = 0, yellow = 0.5, green = 1); a time
step without a pose says "not found"; a frame that could not be decoded is a grey tile.
Poses of several animals (an animal axis): each animal has its own colour
(:data:`ANIMAL_COLOURS`): its limbs and the rings around its keypoints, with its name next
to it; the keypoints' fill stays the confidence colour. The
3D panel looks at the poses from a fixed virtual camera (above and to the side of their
median position) over a floor grid in the plane through the lowest keypoints.
"""

from __future__ import annotations

import logging
from collections.abc import Mapping, Sequence
from pathlib import Path

import cv2
import numpy as np

from freipose.errors import FreiPoseError
from freipose.geometry.camera import Camera, CameraRig
from freipose.geometry.projection import project
from freipose.io.poses import PoseData
from freipose.io.video import VideoWriter
from freipose.predict.reader import SyncReader
from freipose.progress import progress_bar
from freipose.skeleton import Skeleton

log = logging.getLogger(__name__)


class RenderError(FreiPoseError):
    """An overlay cannot be rendered as asked (e.g. frames without predictions)."""


FONT = cv2.FONT_HERSHEY_SIMPLEX
#: BGR colours of the animals of poses with an animal axis, in order (blue, magenta, orange,
#: cyan, then again)
ANIMAL_COLOURS: tuple[tuple[int, int, int], ...] = (
    (255, 120, 40), (200, 60, 230), (20, 140, 255), (230, 230, 40),
)  # fmt: skip


def animal_colour(a: int) -> tuple[int, int, int]:
    """The BGR colour of animal ``a`` (:data:`ANIMAL_COLOURS`, repeating)."""
    return ANIMAL_COLOURS[a % len(ANIMAL_COLOURS)]


def confidence_color(conf: float) -> tuple[int, int, int]:
    """BGR colour for a confidence in [0, 1]: red -> yellow -> green."""
    c = float(np.clip(conf if np.isfinite(conf) else 0.0, 0.0, 1.0))
    r = 255 if c < 0.5 else int(round(255 * (1 - c) * 2))
    g = int(round(255 * min(1.0, 2 * c)))
    return (0, g, r)


def draw_label(img: np.ndarray, text: str, org: tuple[int, int], scale: float) -> None:
    """White ``text`` on a dark box, baseline starting at ``org`` (pixels), onto ``img``."""
    (w, h), base = cv2.getTextSize(text, FONT, scale, 1)
    x, y = org
    box = img[max(y - h - 4, 0) : y + base + 2, max(x - 4, 0) : x + w + 4]
    box[:] = (0.35 * box).astype(np.uint8)
    cv2.putText(img, text, org, FONT, scale, (255, 255, 255), 1, cv2.LINE_AA)


def _codec(output: str | Path) -> str | None:
    """H.264 for an .mp4 overlay (it plays in web browsers); the suffix's codec otherwise."""
    return "h264" if Path(output).suffix.lower() == ".mp4" else None


def _limbs(skeleton: Skeleton | None, k: int) -> list[tuple[tuple[int, ...], tuple[int, ...]]]:
    if skeleton is None:
        return []
    return [(tuple(a), tuple(b)) for a, b in skeleton.limbs if max(*a, *b) < k]


def draw_skeleton_2d(
    img: np.ndarray,
    uv: np.ndarray,
    conf: np.ndarray,
    limbs: Sequence[tuple[tuple[int, ...], tuple[int, ...]]],
    radius: int = 3,
    thickness: int = 2,
    colour: tuple[int, int, int] | None = None,
) -> None:
    """Draw keypoints (K, 2) pixels with confidences (K,) and limbs onto ``img`` in place.

    ``colour``: the animal's colour (limbs and keypoint rings; None: limbs by confidence,
    black rings).
    """
    h, w = img.shape[:2]
    lim = 4 * max(h, w)

    def pt(p: np.ndarray) -> tuple[int, int] | None:
        if not np.isfinite(p).all() or np.abs(p).max() > lim:
            return None
        return int(round(p[0])), int(round(p[1]))

    for a, b in limbs:
        pa, pb = pt(uv[list(a)].mean(0)), pt(uv[list(b)].mean(0))
        if pa is None or pb is None:
            continue
        c = min(conf[list(a)].min(), conf[list(b)].min())
        cv2.line(img, pa, pb, colour or confidence_color(c), thickness, cv2.LINE_AA)
    for k in range(len(uv)):
        p = pt(uv[k])
        if p is not None:
            cv2.circle(img, p, radius, confidence_color(conf[k]), -1, cv2.LINE_AA)
            ring = (colour, 2) if colour is not None else ((0, 0, 0), 1)
            cv2.circle(img, p, radius + ring[1] - 1, ring[0], ring[1], cv2.LINE_AA)


def draw_animals_2d(
    img: np.ndarray,
    uv: np.ndarray,
    conf: np.ndarray,
    limbs: Sequence[tuple[tuple[int, ...], tuple[int, ...]]],
    names: Sequence[str] | None,
    radius: int = 3,
    thickness: int = 2,
) -> None:
    """Draw the skeletons of A animals, (A, K, 2) pixels and (A, K) confidences, in place.

    ``names``: the animals (each in its colour, named next to its keypoints); None: one
    animal drawn as :func:`draw_skeleton_2d` draws it.
    """
    if names is None:
        draw_skeleton_2d(img, uv[0], conf[0], limbs, radius, thickness)
        return
    h, w = img.shape[:2]
    for a, name in enumerate(names):
        col = animal_colour(a)
        draw_skeleton_2d(img, uv[a], conf[a], limbs, radius, thickness, col)
        ok = np.isfinite(uv[a]).all(-1) & (np.abs(uv[a]) < 4 * max(h, w)).all(-1)
        if ok.any():
            x, y = uv[a][ok].min(0)
            org = (int(np.clip(x, 0, w - 40)), int(np.clip(y - 6, 12, h - 4)))
            cv2.putText(img, name, org, FONT, 0.45, col, 1, cv2.LINE_AA)


class Panel3D:
    """A fixed virtual camera that draws 3D poses over a floor grid.

    Args:
        poses: (T, K, 3) all poses to be shown (used to place the camera), mm.
        size: panel (width, height) in pixels.
        up: world up vector.
    """

    def __init__(self, poses: np.ndarray, size: tuple[int, int], up: np.ndarray):
        self.size = (int(size[0]), int(size[1]))
        up = np.asarray(up, np.float64)
        self.up = up / np.linalg.norm(up)
        pts = poses.reshape(-1, 3)
        pts = pts[np.isfinite(pts).all(-1)]
        if len(pts) == 0:
            pts = np.zeros((1, 3))
        self.target = np.median(pts, axis=0)
        spread = (
            np.percentile(np.linalg.norm(pts - self.target, axis=-1), 95) if len(pts) > 1 else 0
        )
        extent = max(float(spread), 100.0)
        heights = pts @ self.up
        self.floor = float(np.percentile(heights, 2)) if len(pts) > 1 else float(heights[0])
        a = self._side_axis()
        direction = 0.8 * a + 0.6 * self.up
        focal = 0.9 * min(self.size)
        dist = 1.8 * extent * focal / min(self.size) + 1.0
        self.camera = Camera.look_at(
            "panel3d",
            self.target + dist * direction,
            self.target,
            self.size,
            focal,
            up=tuple(self.up),
        )
        self.extent = extent

    def _side_axis(self) -> np.ndarray:
        ref = np.array([1.0, 0.0, 0.0]) if abs(self.up[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
        side = ref - (ref @ self.up) * self.up
        rot = np.cross(self.up, side)
        v = side + rot
        return v / np.linalg.norm(v)

    def draw(
        self,
        pose: np.ndarray,
        conf: np.ndarray,
        limbs: Sequence[tuple[tuple[int, ...], tuple[int, ...]]],
        label: str = "3D",
        names: Sequence[str] | None = None,
    ) -> np.ndarray:
        """The 3D panel image (H, W, 3) BGR of ``pose`` (K, 3) with confidences (K,).

        With ``names``, the poses of those animals: (A, K, 3) and (A, K), each in its colour.
        """
        w, h = self.size
        img = np.full((h, w, 3), 30, np.uint8)
        # floor grid in the plane through the lowest keypoints
        e1 = self._side_axis()
        e2 = np.cross(self.up, e1)
        o = self.target - ((self.target @ self.up) - self.floor) * self.up
        step = 10 ** np.floor(np.log10(self.extent / 2))
        n = int(np.ceil(1.2 * self.extent / step))
        for i in range(-n, n + 1):
            for ea, eb in ((e1, e2), (e2, e1)):
                p0 = o + i * step * ea - n * step * eb
                p1 = o + i * step * ea + n * step * eb
                uv = project(np.stack([p0, p1]), self.camera)
                if np.isfinite(uv).all() and np.abs(uv).max() < 1e5:
                    q0, q1 = (tuple(int(v) for v in np.round(q)) for q in uv)
                    cv2.line(img, q0, q1, (70, 70, 70), 1, cv2.LINE_AA)
        if np.isfinite(pose).any():
            uv = project(pose.astype(np.float64), self.camera)
            if names is None:
                draw_skeleton_2d(img, uv, conf, limbs, radius=4, thickness=2)
            else:
                draw_animals_2d(img, uv, conf, limbs, names, radius=4, thickness=2)
        cv2.putText(img, label, (8, 22), FONT, 0.6, (230, 230, 230), 1, cv2.LINE_AA)
        return img


def _fit(img: np.ndarray, width: int) -> tuple[np.ndarray, float]:
    s = width / img.shape[1]
    return cv2.resize(img, (width, int(round(img.shape[0] * s))), interpolation=cv2.INTER_AREA), s


def render_overlay(
    videos: Sequence[str | Path],
    rig: CameraRig,
    data: PoseData,
    output: str | Path,
    frames: tuple[int, int] | None = None,
    tile_width: int = 480,
    show_3d: bool = True,
    progress: bool = True,
) -> Path:
    """Write an overlay video.

    Args:
        videos: one video per camera of ``rig`` (the cameras to show, in order).
        rig: those cameras.
        data: the poses (``frame_index`` says which video frame each row belongs to).
        output: the video to write (.mp4: H.264 for web browsers, .avi MJPG, .mkv lossless).
        frames: video frame range [start, stop) to render; default all rows of ``data``.
        tile_width: width in pixels of each view tile.
        show_3d: add the 3D panel.
        progress: show a progress bar.

    Returns:
        ``output``.

    Raises:
        RenderError: the frame range holds no predicted frame.
    """
    fi = data.frame_index
    a, b = (int(fi.min()), int(fi.max()) + 1) if frames is None else frames
    rows = np.flatnonzero((fi >= a) & (fi < b))
    if len(rows) == 0:
        raise RenderError(
            f"frames {a}:{b} hold no predictions; the poses cover frames {fi.min()}..{fi.max()}"
        )
    a, b = int(fi[rows].min()), int(fi[rows].max()) + 1
    row_of = {int(fi[r]): int(r) for r in rows}
    K, A = len(data.keypoints), data.num_animals
    poses, confs = data.animal_poses()  # (T, A, K, 3), (T, A, K)
    names = data.individuals
    limbs = _limbs(data.skeleton, K)
    C = len(rig)
    tiles_h = [int(round(cam.height * tile_width / cam.width)) for cam in rig]
    tile_h = max(tiles_h)
    n_tiles = C + (1 if show_3d else 0)
    cols = int(np.ceil(np.sqrt(n_tiles)))
    nrows = int(np.ceil(n_tiles / cols))
    W, H = cols * tile_width, nrows * tile_h
    W += W % 2
    H += H % 2
    panel = Panel3D(data.poses[rows], (tile_width, tile_h), data.up) if show_3d else None
    shapes = [(cam.height, cam.width) for cam in rig]
    bar = progress_bar(total=b - a, unit="frame", desc="render", disable=not progress, leave=False)
    with (
        bar,
        VideoWriter(output, data.fps, (W, H), codec=_codec(output)) as writer,
        SyncReader(list(videos), a, b, 1, shapes) as reader,
    ):
        for fb in reader:
            i = int(fb.frame_index[0])
            r = row_of.get(i)
            pose = poses[r] if r is not None else np.full((A, K, 3), np.nan)
            conf = confs[r] if r is not None else np.zeros((A, K))
            canvas = np.zeros((H, W, 3), np.uint8)
            uv_all = np.moveaxis(rig.project(pose.astype(np.float64)), 1, 0)  # (C, A, K, 2)
            for c, cam in enumerate(rig):
                if fb.valid[0, c]:
                    img = fb.images[c][0].copy()
                    tile, s = _fit(img, tile_width)
                    draw_animals_2d(tile, uv_all[c] * s + (s - 1) / 2, conf, limbs, names)
                else:
                    tile = np.full((tiles_h[c], tile_width, 3), 90, np.uint8)
                    msg_at = (8, tiles_h[c] // 2)
                    cv2.putText(tile, "frame missing", msg_at, FONT, 0.6, (230, 230, 230), 1)
                label = f"{cam.name}  frame {i}"
                draw_label(tile, label, (8, 20), 0.5)
                if not np.isfinite(pose).any():
                    cv2.putText(tile, "not found", (8, 44), FONT, 0.6, (0, 0, 255), 2, cv2.LINE_AA)
                y, x = divmod(c, cols)
                y0, x0 = y * tile_h, x * tile_width
                canvas[y0 : y0 + tile.shape[0], x0 : x0 + tile_width] = tile
            if panel is not None:
                y, x = divmod(C, cols)
                mean_c = float(np.mean(conf)) if K else 0.0
                label = f"3D  mean confidence {mean_c:.2f}"
                view = (
                    panel.draw(pose[0], conf[0], limbs, label)
                    if names is None
                    else panel.draw(pose, conf, limbs, label, names)
                )
                if tile_h >= 150:
                    view[-34:] = confidence_legend(tile_width)
                canvas[y * tile_h : (y + 1) * tile_h, x * tile_width : (x + 1) * tile_width] = view
            writer.write(canvas)
            bar.update(1)
    return Path(output)


def confidence_legend(width: int, height: int = 34) -> np.ndarray:
    """A legend strip (height, width, 3) BGR: the confidence colours from 0 to 1, labelled."""
    img = np.full((height, width, 3), 30, np.uint8)
    x0, x1 = 110, max(width - 30, 140)
    for x in range(x0, x1):
        img[6:16, x] = confidence_color((x - x0) / max(x1 - x0 - 1, 1))
    cv2.putText(img, "confidence", (8, 16), FONT, 0.45, (230, 230, 230), 1, cv2.LINE_AA)
    for v in (0.0, 0.5, 1.0):
        x = int(round(x0 + v * (x1 - x0 - 1))) - 8
        cv2.putText(img, f"{v:g}", (x, 30), FONT, 0.4, (230, 230, 230), 1, cv2.LINE_AA)
    return img[:, :width]


def _crop_box(uv: np.ndarray, size: tuple[int, int], margin: float) -> tuple[int, int, int]:
    """Square crop ``(x0, y0, side)`` around the finite points ``uv`` (K, 2) inside the image."""
    w, h = size
    ok = np.isfinite(uv).all(-1) & (np.abs(uv) < 4 * max(w, h)).all(-1)
    if not ok.any():
        return 0, 0, min(w, h)
    lo, hi = uv[ok].min(0), uv[ok].max(0)
    side = int(np.clip(max(hi - lo) * (1 + 2 * margin), 48, min(w, h)))
    cx, cy = (lo + hi) / 2
    x0 = int(np.clip(round(cx - side / 2), 0, w - side))
    y0 = int(np.clip(round(cy - side / 2), 0, h - side))
    return x0, y0, side


def still_tile(
    img: np.ndarray,
    uv: np.ndarray,
    conf: np.ndarray,
    limbs: Sequence[tuple[tuple[int, ...], tuple[int, ...]]],
    label: str,
    tile: int = 360,
    margin: float = 0.35,
    names: Sequence[str] | None = None,
) -> np.ndarray:
    """One camera's still (tile, tile, 3) BGR: the view cropped to the animal, full view inset.

    Args:
        img: the camera image (H, W, 3) BGR.
        uv: (K, 2) projected keypoints, pixels of ``img``; (A, K, 2) with ``names``.
        conf: (K,) confidences (the colours); (A, K) with ``names``.
        limbs: the skeleton's limbs.
        label: text in the top-left corner (the camera name).
        tile: output side in pixels; the crop is scaled to it and the skeleton drawn after.
        margin: crop margin around the keypoints, as a share of their extent.
        names: the animals of poses with an animal axis (cropped to them all), or None.
    """
    h, w = img.shape[:2]
    if names is None:
        uv, conf = uv[None], conf[None]
    x0, y0, side = _crop_box(uv.reshape(-1, 2), (w, h), margin)
    s = tile / side
    out = cv2.resize(img[y0 : y0 + side, x0 : x0 + side], (tile, tile),
                     interpolation=cv2.INTER_CUBIC)  # fmt: skip
    draw_animals_2d(out, (uv - (x0, y0)) * s + (s - 1) / 2, conf, limbs, names, 5, 2)
    iw = tile // 3
    ih = int(round(h * iw / w))
    inset = cv2.resize(img, (iw, ih), interpolation=cv2.INTER_AREA)
    r = iw / w
    p0 = (int(x0 * r), int(y0 * r))
    p1 = (int((x0 + side) * r) - 1, int((y0 + side) * r) - 1)
    cv2.rectangle(inset, p0, p1, (255, 255, 255), 1)
    out[2 : 2 + ih, tile - iw - 2 : tile - 2] = inset
    cv2.rectangle(out, (tile - iw - 3, 1), (tile - 2, 2 + ih), (255, 255, 255), 1)
    draw_label(out, label, (8, 22), 0.6)
    return out


def render_stills(
    videos: Sequence[str | Path],
    rig: CameraRig,
    data: PoseData,
    frames: Sequence[int],
    paths: Sequence[str | Path],
    tile: int = 360,
) -> list[Path]:
    """Still PNGs of video frames: every camera cropped to the animal, a colour legend.

    Args:
        videos: one video per camera of ``rig``, in its order.
        rig: the cameras.
        data: the predicted poses.
        frames: video frame numbers, each with a prediction in ``data``.
        paths: one output PNG per frame.
        tile: side of each camera's tile in pixels.

    Returns:
        The written paths.

    Raises:
        RenderError: a frame has no prediction.
    """
    from freipose.io.atomic import atomic_path
    from freipose.io.video import FrameSource

    row_of = {int(f): r for r, f in enumerate(data.frame_index)}
    limbs = _limbs(data.skeleton, len(data.keypoints))
    cols = min(4, len(rig))
    rows = int(np.ceil(len(rig) / cols))
    sources = [FrameSource(v) for v in videos]
    written = []
    try:
        for frame, path in zip(frames, paths):
            if int(frame) not in row_of:
                raise RenderError(f"frame {frame} has no prediction in the poses")
            r = row_of[int(frame)]
            uv_all = rig.project(data.poses[r].astype(np.float64))  # (C, K, 2) / (A, C, K, 2)
            if data.individuals is not None:
                uv_all = np.moveaxis(uv_all, 1, 0)
            canvas = np.full((rows * tile, cols * tile, 3), 30, np.uint8)
            for c, (cam, src) in enumerate(zip(rig, sources)):
                label = f"{cam.name}  frame {frame}"
                t = still_tile(src.read(int(frame)), uv_all[c], data.confidence[r], limbs,
                               label, tile, names=data.individuals)  # fmt: skip
                y, x = divmod(c, cols)
                canvas[y * tile : (y + 1) * tile, x * tile : (x + 1) * tile] = t
            img = np.vstack([canvas, confidence_legend(canvas.shape[1])])
            ok, png = cv2.imencode(".png", img)
            if not ok:
                raise RenderError(f"{path}: OpenCV cannot encode the still as PNG")
            with atomic_path(path) as tmp:
                tmp.write_bytes(png.tobytes())
            written.append(Path(path))
    finally:
        for src in sources:
            src.close()
    return written


def session_mismatches(data: PoseData, session: Path, videos: Mapping[str, Path]) -> list[str]:
    """How the poses ``data`` disagree with the session folder ``session`` (empty: they fit).

    Compared: the session name and the video file names recorded in the poses'
    provenance, the cameras of the poses' calibration, and the frame count (the poses must
    not cover frames beyond the session's longest video).
    """
    from freipose.io.video import FrameSource

    prov = dict(data.provenance)
    problems = []
    name = session.resolve().name
    if "session" in prov and str(prov["session"]) != name:
        problems.append(f"the poses are of session {prov['session']!r}, the videos of {name!r}")
    recorded = prov.get("videos")
    if isinstance(recorded, dict):
        other = {c: f for c, f in recorded.items() if c in videos and videos[c].name != str(f)}
        if other:
            problems.append(
                "the poses were predicted from the videos "
                + ", ".join(f"{c}: {f}" for c, f in sorted(other.items()))
                + ", the session has "
                + ", ".join(f"{c}: {videos[c].name}" for c in sorted(other))
            )
    if data.calibration is not None and not set(data.calibration.names) & set(videos):
        problems.append(
            f"the poses' cameras {data.calibration.names} are not among the session's videos "
            f"{sorted(videos)}"
        )
    lengths = []
    for path in videos.values():
        with FrameSource(path) as src:
            lengths.append(src.num_frames)
    last = int(data.frame_index.max()) if data.num_frames else -1
    if lengths and last >= max(lengths):
        problems.append(
            f"the poses cover frames up to {last}, the session's videos have {max(lengths)} frames"
        )
    return problems


def check_session(
    data: PoseData, poses: Path, session: Path, videos: Mapping[str, Path], force: bool
) -> list[str]:
    """Refuse poses that belong to another session, unless ``force``.

    Returns:
        The mismatches found (see :func:`session_mismatches`), for a warning under ``force``.

    Raises:
        RenderError: the poses do not fit the session and ``force`` is false.
    """
    problems = session_mismatches(data, session, videos)
    if problems and not force:
        raise RenderError(
            f"{poses} does not belong to the session {session}: "
            + "; ".join(problems)
            + ". Render the poses of this session, or pass --force to draw them anyway"
        )
    return problems
