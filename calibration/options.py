"""The calibration's options (:class:`CalibrationOptions`) and their allowed values."""

from __future__ import annotations

from dataclasses import dataclass

from freipose.geometry import CameraRig

__all__ = ["ASPECT_MODES", "PRINCIPAL_POINT_MODES", "CalibrationOptions"]

PRINCIPAL_POINT_MODES = ("auto", "free", "centre")
ASPECT_MODES = ("auto", "free", "square")


@dataclass(frozen=True)
class CalibrationOptions:
    """Solver options.

    Attributes:
        origin_frame: video frame whose board pose defines the world (board on the floor: origin
            at the board's top-left pattern corner, x along the board's rows, z up out of the
            floor); ``None`` = the first camera's frame.
        up: (3,) the world's up direction, stored with the calibration (only without
            ``origin_frame``, whose world has z up); ``None`` = unknown.
        intrinsics_only: stop after per-camera intrinsics (extrinsics are identity).
        fixed_intrinsics: a rig whose K and distortion are used (and kept fixed) for every
            camera of the same name.
        dist_model: ``auto`` (default: k1 k2, plus p1 p2 for a camera where the tangential
            terms are significant), ``none``, ``k1``, ``k1k2``, ``k1k2p`` (k1 k2 p1 p2) or
            ``full`` (k1 k2 p1 p2 k3).
        principal_point: ``auto`` (default: the image centre unless the bundle adjustment
            finds a significant offset), ``free`` or ``centre`` (fixed at
            ``((w - 1) / 2, (h - 1) / 2)``).
        aspect: ``auto`` (default: fy = fx, square pixels, unless the bundle adjustment finds
            them significantly different), ``free`` (fx and fy estimated separately) or
            ``square`` (always fy = fx).
        jobs: detection processes, and threads that initialise the cameras (default: CPU
            count).
        max_views: views per camera for the intrinsics initialisation.
        loss: robust loss of the bundle adjustment.
        f_scale: scale (px) of the robust loss; ``None`` estimates it from the detection
            noise (see :func:`freipose.calibration.bundle.bundle_adjust`).
        outlier_px: minimum rejection threshold (px); detections further than
            ``max(outlier_px, 5 σ_c)`` from their projection are rejected, ``σ_c`` being
            their camera's own noise level. The default, 2 px, keeps the corners of blurred
            views (motion blur in part of a camera's views) that a quiet camera's own noise
            level would reject, while corners with a wrong id (a square or more off) are
            still removed.
        solver: ``lm`` (Schur-complement Levenberg-Marquardt) or ``scipy`` (least_squares).
        progress: show a progress bar while detecting.
        refine_board: after the bundle adjustment, correct every board point's position in
            the board plane (printing errors, and each corner's own detection bias, which is
            the same in every view) and adjust again; once before and once after the model
            selection (see :func:`freipose.calibration.bundle.board_point_offsets`; the board
            keeps its printed size).
        view_weights: weight every board view's detections by that view's own noise level
            (σ / σ_view, estimated from its residuals after the first round; see
            :func:`freipose.calibration.robust.view_noise_scales`): blurred or steep views
            count less.
        accept_implausible: return a calibration that fails the plausibility checks
            (:mod:`freipose.calibration.plausibility`) with its findings, marked as suspect
            in its metadata, instead of raising
            :class:`~freipose.calibration.plausibility.ImplausibleCalibrationError`.
    """

    origin_frame: int | None = None
    up: tuple[float, float, float] | None = None
    intrinsics_only: bool = False
    fixed_intrinsics: CameraRig | None = None
    dist_model: str = "auto"
    principal_point: str = "auto"
    aspect: str = "auto"
    jobs: int | None = None
    max_views: int = 40
    loss: str = "huber"
    f_scale: float | None = None
    outlier_px: float = 2.0
    solver: str = "lm"
    progress: bool = True
    refine_board: bool = True
    view_weights: bool = True
    accept_implausible: bool = False
