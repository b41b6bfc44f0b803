"""``freipose labels check``: find mislabeled points.

Per 2D label the reprojection error of the label's robust 3D point (re-triangulated from
the 2D labels with RANSAC over views; the stored 3D point where fewer than two views
exist). Suspicious labels, each with a *severity* (how many times over its threshold):

* ``reprojection``: error above ``max_error`` pixels (severity = error / max_error);
* ``swapped``: in one view, a left/right keypoint pair fits the other's projection much
  better than its own (severity = error saved by swapping / max_error);
* ``limb_length``: a limb more than ``limb_tolerance`` (relative) and 4 robust standard
  deviations away from its median over the dataset (severity = relative deviation /
  limb_tolerance).

The list is sorted worst first; :func:`write_report` writes it as ``suspicious.csv``,
all errors as ``reprojection_errors.csv`` (formats in ``docs/formats.md``), figures of the
error distribution per keypoint and camera, and image crops of the worst labels.
"""

from __future__ import annotations

import csv
import io
import logging
import re
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from freipose.errors import FreiPoseError
from freipose.geometry.triangulation import reprojection_errors, triangulate_robust
from freipose.io.atomic import atomic_path, atomic_write_text
from freipose.io.figures import new_figure, save_figure
from freipose.io.labels import LabelSet
from freipose.skeleton import Skeleton, infer_symmetry

log = logging.getLogger(__name__)

CSV_COLUMNS = (
    "rank",
    "kind",
    "severity",
    "index",
    "session",
    "frame_index",
    "camera",
    "keypoint",
    "value",
    "threshold",
    "detail",
)


@dataclass(frozen=True)
class Suspicious:
    """One suspicious label (camera is "" for 3D findings such as limb lengths)."""

    kind: str
    severity: float
    index: int
    session: str
    frame_index: int
    camera: str
    keypoint: str
    value: float
    threshold: float
    detail: str


@dataclass(frozen=True, eq=False)
class CheckResult:
    """The result of :func:`check_labels`.

    Attributes:
        errors: (N, V, K) reprojection errors in px (NaN: no label or no 3D point).
        points3d: (N, K, 3) the 3D points used.
        projections: (N, V, K, 2) their projections.
        suspicious: the suspicious labels, worst first.
    """

    errors: np.ndarray
    points3d: np.ndarray
    projections: np.ndarray
    suspicious: list[Suspicious]


class LabelCheckError(FreiPoseError):
    """Labels cannot be checked with the given skeleton; the message says why."""


@dataclass(frozen=True)
class Reprojection:
    """Labels reprojected from their robust 3D points.

    Attributes:
        errors: (N, V, K) reprojection errors in px (NaN: no label or no 3D point).
        projections: (N, V, K, 2) projections of the 3D points.
        points3d: (N, K, 3) the 3D points: re-triangulated, else the stored ones.
    """

    errors: np.ndarray
    projections: np.ndarray
    points3d: np.ndarray


def reproject_labels(labels: LabelSet, threshold: float = 20.0) -> Reprojection:
    """Re-triangulate every session's labels robustly and reproject them.

    Where fewer than two views agree, the stored 3D point is used; sessions without
    cameras keep NaN errors.

    Args:
        labels: the labels.
        threshold: RANSAC inlier threshold (px).

    Returns:
        The errors, projections and 3D points.
    """
    n, v, k = labels.points2d.shape[:3]
    errors = np.full((n, v, k), np.nan)
    proj = np.full((n, v, k, 2), np.nan)
    X = labels.points3d.copy()
    for sess in sorted(set(labels.session)):
        rig = labels.rig_for(sess)
        if rig is None:
            continue
        rows = np.flatnonzero(labels.session == sess)
        cols = [labels.cameras.index(c) for c in rig.names]
        obs = np.moveaxis(labels.points2d[rows][:, cols], 1, 2)  # (n, K, C, 2)
        Xr, _ = triangulate_robust(obs, rig, threshold=threshold, refine=True)
        Xs = np.where(np.isfinite(Xr).all(-1, keepdims=True), Xr, X[rows])
        X[rows] = Xs
        pr = rig.project(Xs)  # (n, C, K, 2)
        proj[np.ix_(rows, cols)] = pr
        errors[np.ix_(rows, cols)] = np.moveaxis(reprojection_errors(Xs, obs, rig), 2, 1)
    return Reprojection(errors, proj, X)


def _finding(
    labels: LabelSet,
    kind: str,
    severity: float,
    i: int,
    c: int | None,
    keypoint: str,
    value: float,
    threshold: float,
    detail: str,
) -> Suspicious:
    """A suspicious label of row ``i`` and camera ``c`` (None: a 3D finding)."""
    return Suspicious(
        kind,
        float(severity),
        int(i),
        str(labels.session[i]),
        int(labels.frame_index[i]),
        labels.cameras[c] if c is not None else "",
        keypoint,
        float(value),
        float(threshold),
        detail,
    )


@dataclass(frozen=True)
class SwapFindings:
    """Left/right pairs that fit better swapped.

    Attributes:
        found: one finding per swapped pair in one view.
        labels: (row, camera, keypoint) of every label in a swapped pair.
    """

    found: list[Suspicious]
    labels: frozenset[tuple[int, int, int]]


def swapped_pairs(
    labels: LabelSet, symmetry: Sequence[tuple[int, int]], rep: Reprojection, max_error: float
) -> SwapFindings:
    """Find left/right pairs whose labels fit the other keypoint's projection much better.

    Args:
        labels: the labels.
        symmetry: (left, right) keypoint index pairs.
        rep: the labels' reprojection.
        max_error: reprojection error (px) above which a label is suspicious.

    Returns:
        The findings and the labels they cover.
    """
    errors, proj = rep.errors, rep.projections
    found: list[Suspicious] = []
    swapped = set()
    for a, b in symmetry:
        ea, eb = errors[:, :, a], errors[:, :, b]
        sw_a = np.linalg.norm(labels.points2d[:, :, a] - proj[:, :, b], axis=-1)
        sw_b = np.linalg.norm(labels.points2d[:, :, b] - proj[:, :, a], axis=-1)
        own, other = ea + eb, sw_a + sw_b
        hit = (own > max_error) & (other < 0.5 * own)
        for i, c in np.argwhere(hit):
            swapped.update({(i, c, a), (i, c, b)})
            pair = f"{labels.keypoints[a]} <-> {labels.keypoints[b]}"
            found.append(
                _finding(
                    labels,
                    "swapped",
                    (own[i, c] - other[i, c]) / max_error,
                    i,
                    c,
                    pair,
                    own[i, c],
                    max_error,
                    f"left/right swapped? errors {own[i, c]:.1f} px as labeled, "
                    f"{other[i, c]:.1f} px swapped",
                )
            )
    return SwapFindings(found, frozenset(swapped))


def reprojection_findings(
    labels: LabelSet, errors: np.ndarray, max_error: float, skip: frozenset
) -> list[Suspicious]:
    """Labels further than ``max_error`` px from the reprojection of their 3D point.

    Args:
        labels: the labels.
        errors: (N, V, K) reprojection errors in px.
        max_error: the threshold in px.
        skip: (row, camera, keypoint) already reported (as swapped).

    Returns:
        One finding per label above the threshold, in row, camera, keypoint order.
    """
    found = []
    for i, c, kk in np.argwhere(errors > max_error):
        if (i, c, kk) in skip:
            continue
        e = errors[i, c, kk]
        found.append(
            _finding(
                labels,
                "reprojection",
                e / max_error,
                i,
                c,
                labels.keypoints[kk],
                e,
                max_error,
                f"label is {e:.1f} px from the reprojection of its 3D point",
            )
        )
    return found


def limb_findings(
    labels: LabelSet, skeleton: Skeleton, points3d: np.ndarray, limb_tolerance: float
) -> list[Suspicious]:
    """Limbs far (relative and robust z-score > 4) from their median length.

    Args:
        labels: the labels (at least five rows, else nothing is found).
        skeleton: the limbs.
        points3d: (N, K, 3) the labels' 3D points.
        limb_tolerance: relative deviation above which a limb is suspicious.

    Returns:
        One finding per suspicious limb and row.
    """
    if not skeleton.limbs or len(points3d) < 5:
        return []
    L = skeleton.limb_lengths(points3d)  # (N, L)
    med = np.nanmedian(L, axis=0)
    mad = 1.4826 * np.nanmedian(np.abs(L - med), axis=0) + 1e-9
    rel = np.abs(L - med) / np.maximum(med, 1e-9)
    z = np.abs(L - med) / mad
    found = []
    for i, li in np.argwhere((rel > limb_tolerance) & (z > 4)):
        ends = ["+".join(skeleton.keypoints[j] for j in end) for end in skeleton.limbs[li]]
        found.append(
            _finding(
                labels,
                "limb_length",
                rel[i, li] / limb_tolerance,
                i,
                None,
                f"{ends[0]} - {ends[1]}",
                L[i, li],
                med[li],
                f"limb {L[i, li]:.1f} mm vs median {med[li]:.1f} mm ({100 * rel[i, li]:.0f}% off)",
            )
        )
    return found


def check_labels(
    labels: LabelSet,
    skeleton: Skeleton | None = None,
    max_error: float = 10.0,
    limb_tolerance: float = 0.3,
    threshold: float = 20.0,
) -> CheckResult:
    """Reprojection errors and suspicious labels (see the module docstring).

    Args:
        labels: the labels.
        skeleton: limbs and symmetry pairs (its keypoints must be the labels' keypoints);
            without one, symmetry pairs come from left/right in the names and limbs are
            not checked.
        max_error: reprojection error (px) above which a label is suspicious.
        limb_tolerance: relative limb length deviation above which a limb is suspicious.
        threshold: RANSAC inlier threshold (px) for re-triangulation.

    Returns:
        The errors, 3D points, projections and suspicious labels, worst first.

    Raises:
        LabelCheckError: the skeleton's keypoints are not the labels' keypoints.
    """
    if skeleton is not None and tuple(skeleton.keypoints) != tuple(labels.keypoints):
        raise LabelCheckError(
            f"skeleton {skeleton.name!r} keypoints {list(skeleton.keypoints)} differ from the "
            f"labels' keypoints {list(labels.keypoints)}; import the labels with this skeleton"
        )
    sym = list(skeleton.symmetry) if skeleton is not None else infer_symmetry(labels.keypoints)
    rep = reproject_labels(labels, threshold)
    swaps = swapped_pairs(labels, sym, rep, max_error)
    found = swaps.found + reprojection_findings(labels, rep.errors, max_error, swaps.labels)
    if skeleton is not None:
        found += limb_findings(labels, skeleton, rep.points3d, limb_tolerance)
    found.sort(key=lambda s: -s.severity)
    return CheckResult(rep.errors, rep.points3d, rep.projections, found)


def suspicious_csv_text(items: Sequence[Suspicious]) -> str:
    """The text of ``suspicious.csv`` (columns :data:`CSV_COLUMNS`, rank 1 first).

    Args:
        items: the suspicious labels, worst first.

    Returns:
        The CSV text.
    """
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(CSV_COLUMNS)
    for r, s in enumerate(items, start=1):
        w.writerow(
            [
                r,
                s.kind,
                f"{s.severity:.3f}",
                s.index,
                s.session,
                s.frame_index,
                s.camera,
                s.keypoint,
                f"{s.value:.3f}",
                f"{s.threshold:.3f}",
                s.detail,
            ]
        )
    return buf.getvalue()


def errors_csv_text(labels: LabelSet, errors: np.ndarray) -> str:
    """The text of ``reprojection_errors.csv``: one row per finite error.

    Args:
        labels: the labels.
        errors: (N, V, K) reprojection errors in px.

    Returns:
        The CSV text.
    """
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(["index", "session", "frame_index", "camera", "keypoint", "error_px"])
    for i, c, kk in np.argwhere(np.isfinite(errors)):
        w.writerow(
            [
                i,
                labels.session[i],
                labels.frame_index[i],
                labels.cameras[c],
                labels.keypoints[kk],
                f"{errors[i, c, kk]:.3f}",
            ]
        )
    return buf.getvalue()


def _figures(labels: LabelSet, errors: np.ndarray, out: Path) -> list[Path]:
    """Box plots of the reprojection errors per keypoint and per camera.

    Args:
        labels: the labels.
        errors: (N, V, K) reprojection errors in px.
        out: the report folder.

    Returns:
        The written PNG files.
    """
    written = []
    for axis, names, fname in (
        (2, labels.keypoints, "errors_by_keypoint.png"),
        (1, labels.cameras, "errors_by_camera.png"),
    ):
        data = []
        for j in range(len(names)):
            e = np.take(errors, j, axis=axis).ravel()
            data.append(e[np.isfinite(e)])
        fig = new_figure((max(4, 0.6 * len(names) + 2), 4))
        ax = fig.subplots()
        ax.boxplot([d if len(d) else [np.nan] for d in data], showfliers=True)
        ax.set_xticks(range(1, len(names) + 1), list(names), rotation=60, ha="right")
        ax.set_ylabel("reprojection error (px)")
        ax.set_yscale("symlog", linthresh=1.0)
        ax.set_title(f"label reprojection error per {'keypoint' if axis == 2 else 'camera'}")
        fig.tight_layout()
        written.append(save_figure(fig, out / fname, dpi=80, format="png"))
    return written


def _crops(
    labels: LabelSet,
    result: CheckResult,
    out: Path,
    root: Path,
    n_crops: int,
    half: int = 60,
) -> list[Path]:
    import cv2

    from freipose.io.video import FrameSource, MediaError

    written: list[Path] = []
    sources: dict[tuple[str, str], FrameSource | None] = {}
    for rank, s in enumerate(result.suspicious, start=1):
        if len(written) >= n_crops:
            break
        if not s.camera:
            continue
        key = (s.session, s.camera)
        if key not in sources:
            vid = labels.sessions[s.session].videos.get(s.camera)
            src = None
            if vid is not None:
                p = Path(vid) if Path(vid).is_absolute() else root / vid
                try:
                    src = FrameSource(p)
                except MediaError as exc:
                    log.warning("no crops from %s: %s", p, exc)
            sources[key] = src
        src = sources[key]
        if src is None or s.frame_index >= src.num_frames:
            continue
        img = src.read(s.frame_index).copy()
        c = labels.cameras.index(s.camera)
        kps = [labels.keypoints.index(x) for x in s.keypoint.split(" <-> ")]
        pts = []
        for kk in kps:
            uv, pr = labels.points2d[s.index, c, kk], result.projections[s.index, c, kk]
            pts += [p for p in (uv, pr) if np.isfinite(p).all()]
            if np.isfinite(uv).all() and np.isfinite(pr).all():
                cv2.line(img, _pt(uv), _pt(pr), (0, 255, 255), 1, cv2.LINE_AA)
            if np.isfinite(uv).all():
                cv2.circle(img, _pt(uv), 5, (0, 0, 255), 2, cv2.LINE_AA)
            if np.isfinite(pr).all():
                cv2.drawMarker(img, _pt(pr), (0, 255, 0), cv2.MARKER_CROSS, 12, 2)
        if not pts:
            continue
        ctr = np.mean(pts, axis=0)
        span = max(half, int(np.ptp(np.array(pts), axis=0).max() / 2) + 20)
        x0, y0 = int(ctr[0]) - span, int(ctr[1]) - span
        pad = cv2.copyMakeBorder(img, span, span, span, span, cv2.BORDER_CONSTANT)
        crop = pad[y0 + span : y0 + 3 * span, x0 + span : x0 + 3 * span]
        crop = cv2.resize(crop, (240, 240), interpolation=cv2.INTER_LINEAR)
        name = re.sub(
            r"[^\w.\-]+", "_", f"{rank:03d}_{s.session}_{s.frame_index}_{s.camera}_{s.keypoint}"
        )
        path = out / "worst" / f"{name}.png"
        path.parent.mkdir(parents=True, exist_ok=True)
        with atomic_path(path) as tmp:
            ok, buf = cv2.imencode(".png", crop)
            tmp.write_bytes(buf.tobytes())
        written.append(path)
    for src in sources.values():
        if src is not None:
            src.close()
    return written


def _pt(p: np.ndarray) -> tuple[int, int]:
    return int(round(float(p[0]))), int(round(float(p[1])))


def write_report(
    labels: LabelSet, result: CheckResult, out: str | Path, root: str | Path, n_crops: int = 20
) -> list[Path]:
    """Write the report of a check into folder ``out``.

    The report is ``suspicious.csv``, ``reprojection_errors.csv``, the figures and the
    crops of the worst labels (red circle: label, green cross: reprojection).

    Args:
        labels: the labels.
        result: the check result.
        out: the report folder.
        root: the folder the labels' video paths are relative to.
        n_crops: the most crops to write.

    Returns:
        The written files.
    """
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    atomic_write_text(out / "suspicious.csv", suspicious_csv_text(result.suspicious))
    atomic_write_text(out / "reprojection_errors.csv", errors_csv_text(labels, result.errors))
    written = [out / "suspicious.csv", out / "reprojection_errors.csv"]
    if np.isfinite(result.errors).any():
        written += _figures(labels, result.errors, out)
    written += _crops(labels, result, out, Path(root), n_crops)
    return written
