"""Fixed boxes derived from the labels: where the labeled animal was seen in every camera.

For a new rig, before a detector is trained, and when background subtraction fails (an
animal that rests becomes background), the labels still tell where the animal is: each
camera's box holds every labeled keypoint (its 2D labels and the projections of the 3D
labels) over the labels, plus a margin, and is centred on the projection of the labels'
median centre, so the boxes of all views agree on one 3D point (the multi-view step then
finds that centre in every frame). One cube position serves every frame: fine for a
resting animal or a small arena, not for an animal that roams (train the detector).
The boxes are written as the fixed-boxes TOML file that ``--fixed-boxes`` reads.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from freipose.detect.fallback import FallbackBoxesError, FixedBoxes
from freipose.geometry import CameraRig, project_rig
from freipose.geometry.crops import label_centers
from freipose.io.atomic import atomic_write_text
from freipose.io.labels import LabelSet

MARGIN = 0.1


@dataclass(frozen=True, eq=False)
class LabelBoxes:
    """Per-camera boxes of the labeled animal.

    Attributes:
        boxes: camera -> (x0, y0, x1, y1) full-image pixels.
        center: (3,) the labels' median centre, world mm.
        instants: labeled instants with a 3D centre that were used.
        margin: the margin added on every side, as a fraction of the box's longer side.
    """

    boxes: Mapping[str, tuple[float, float, float, float]]
    center: np.ndarray
    instants: int
    margin: float

    def source(self) -> FixedBoxes:
        """The boxes as a box source (:class:`~freipose.detect.fallback.FixedBoxes`)."""
        return FixedBoxes(self.boxes)


def _points(labels: LabelSet, rig: CameraRig, cam: str) -> np.ndarray:
    """(P, 2) every labeled point of ``cam``: the projected 3D labels, and its 2D labels.

    2D labels count only from sessions filmed by this very camera (their calibration of
    ``cam`` equals the rig's): another rig's camera of the same name sees other pixels.
    """
    parts = []
    if cam in labels.cameras:
        same = [
            s
            for s, info in labels.sessions.items()
            if info.calibration is not None
            and cam in info.calibration.names
            and info.calibration[cam].allclose(rig[cam], rtol=1e-6, atol=1e-6)
        ]
        rows = np.isin(labels.session, same)
        p2 = labels.points2d[rows, labels.cameras.index(cam)].reshape(-1, 2)
        parts.append(p2[np.isfinite(p2).all(-1)])
    p3 = labels.points3d.reshape(-1, 3)
    p3 = p3[np.isfinite(p3).all(-1)]
    if len(p3):
        uv = project_rig(p3[None], rig.subset([cam]))[0, 0]  # (P, 2), NaN behind the camera
        parts.append(uv[np.isfinite(uv).all(-1)])
    return np.concatenate(parts) if parts else np.zeros((0, 2))


def label_boxes(labels: LabelSet, rig: CameraRig, margin: float = MARGIN) -> LabelBoxes:
    """Fixed boxes from the labels (see the module docstring).

    Args:
        labels: labels with 3D points (in the world of ``rig``).
        rig: the cameras to make boxes for.
        margin: added on every side, as a fraction of the box's longer side.

    Returns:
        The boxes; a camera that sees none of the labeled points (or not the centre) gets
        none.

    Raises:
        FallbackBoxesError: no labeled instant has a 3D point, several instants (animals)
            share a frame, or no camera gets a box.
    """
    p3 = labels.points3d
    ok = np.isfinite(p3).all(-1)
    has = ok.any(-1)
    if not has.any():
        raise FallbackBoxesError(
            "the labels have no 3D point to derive fixed boxes from; import them with a "
            "--calibration so that labels seen in two views are triangulated"
        )
    keys = [(str(s), int(f)) for s, f in zip(labels.session[has], labels.frame_index[has])]
    if len(set(keys)) < len(keys):
        s, f = next(k for k in keys if keys.count(k) > 1)
        raise FallbackBoxesError(
            f"the labels hold {keys.count((s, f))} animals in one frame ({s} frame {f}): "
            "boxes from them would place one cube between the animals, and prediction "
            "follows one animal; pass --fixed-boxes FILE with boxes around one animal"
        )
    centres = label_centers(p3[has])  # (n, 3)
    center = np.median(centres, axis=0)
    boxes: dict[str, tuple[float, float, float, float]] = {}
    for cam in rig:
        pts = _points(labels, rig, cam.name)
        c = project_rig(center[None, None], rig.subset([cam.name]))[0, 0, 0]
        if not len(pts) or not np.isfinite(c).all():
            continue
        half = np.maximum(c - pts.min(0), pts.max(0) - c)  # (2,) symmetric about the centre
        half = half + margin * 2 * half.max()
        w, h = cam.size
        x0, y0 = max(c[0] - half[0], -0.5), max(c[1] - half[1], -0.5)
        x1, y1 = min(c[0] + half[0], w - 0.5), min(c[1] + half[1], h - 0.5)
        if x1 > x0 and y1 > y0:
            boxes[cam.name] = (float(x0), float(y0), float(x1), float(y1))
    if not boxes:
        raise FallbackBoxesError(
            f"none of the cameras {list(rig.names)} sees the labeled animal; do the labels "
            "belong to this calibration?"
        )
    return LabelBoxes(boxes, center, int(has.sum()), margin)


def write_fixed_boxes(boxes: LabelBoxes, path: str | Path, source: str = "") -> Path:
    """Write the boxes as a fixed-boxes TOML file (``[boxes] camera = [x0, y0, x1, y1]``).

    Args:
        boxes: the boxes.
        path: the file to write (atomically).
        source: what they were derived from (a comment in the file).

    Returns:
        The path.
    """
    c = boxes.center
    lines = [
        f"# fixed boxes from the labels {source}".rstrip(),
        f"# {boxes.instants} labeled instants, margin {boxes.margin:g}, centred on the labels'"
        f" median centre [{c[0]:.1f}, {c[1]:.1f}, {c[2]:.1f}] mm",
        "[boxes]",
    ]
    for cam, b in boxes.boxes.items():
        vals = ", ".join(f"{v:.1f}" if math.isfinite(v) else "nan" for v in b)
        lines.append(f'"{cam}" = [{vals}]')
    atomic_write_text(Path(path), "\n".join(lines) + "\n")
    return Path(path)
