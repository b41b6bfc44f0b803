"""OpenCV's five-parameter lens distortion in NumPy: distort, derivatives, undistort.

The model maps normalized coordinates ``(x, y)`` (``x/z, y/z`` in the camera) with
``r² = x² + y²`` to::

    xd = x (1 + k1 r² + k2 r⁴ + k3 r⁶) + 2 p1 x y + p2 (r² + 2 x²)
    yd = y (1 + k1 r² + k2 r⁴ + k3 r⁶) + p1 (r² + 2 y²) + 2 p2 x y

:func:`distortion_terms` is the one place that evaluates this polynomial; distortion,
its Jacobian (for undistortion and the bundle adjustment) and undistortion use its parts.
The PyTorch version is :func:`freipose.geometry.torch_ops.distort_normalized`.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from freipose.geometry._checks import check_last

__all__ = [
    "DistortionJacobian",
    "DistortionTerms",
    "distort_normalized",
    "distortion_jacobian",
    "distortion_terms",
    "undistort_normalized",
]


@dataclass(frozen=True)
class DistortionTerms:
    """The parts of the distortion polynomial at points ``(x, y)``, all of shape (...,).

    Attributes:
        r2: ``x² + y²``.
        radial: the radial factor ``1 + k1 r² + k2 r⁴ + k3 r⁶``.
        dx_p1: ``2 p1 x y``, the p1 part of the tangential shift of x.
        dx_p2: ``p2 (r² + 2 x²)``, the p2 part of the tangential shift of x.
        dy_p1: ``p1 (r² + 2 y²)``, the p1 part of the tangential shift of y.
        dy_p2: ``2 p2 x y``, the p2 part of the tangential shift of y.
        xd: distorted x, ``x radial + dx_p1 + dx_p2``.
        yd: distorted y, ``y radial + dy_p1 + dy_p2``.
    """

    r2: np.ndarray
    radial: np.ndarray
    dx_p1: np.ndarray
    dx_p2: np.ndarray
    dy_p1: np.ndarray
    dy_p2: np.ndarray
    xd: np.ndarray
    yd: np.ndarray


@dataclass(frozen=True)
class DistortionJacobian:
    """Derivatives of the distorted coordinates.

    Attributes:
        d_xy: (..., 2, 2) ``d(xd, yd) / d(x, y)``.
        d_dist: (..., 2, 5) ``d(xd, yd) / d(k1, k2, p1, p2, k3)``, or None when not asked for.
    """

    d_xy: np.ndarray
    d_dist: np.ndarray | None


def distortion_terms(x: np.ndarray, y: np.ndarray, dist: np.ndarray) -> DistortionTerms:
    """Evaluate the distortion polynomial at normalized points.

    Args:
        x: (...,) normalized x.
        y: (...,) normalized y.
        dist: (..., 5) coefficients ``(k1, k2, p1, p2, k3)``, broadcastable to ``x``.

    Returns:
        The polynomial's parts and the distorted coordinates, each (...,).
    """
    k1, k2, p1, p2, k3 = (dist[..., i] for i in range(5))
    r2 = x * x + y * y
    radial = 1 + r2 * (k1 + r2 * (k2 + r2 * k3))
    dx_p1 = 2 * p1 * x * y
    dx_p2 = p2 * (r2 + 2 * x * x)
    dy_p1 = p1 * (r2 + 2 * y * y)
    dy_p2 = 2 * p2 * x * y
    xd = x * radial + dx_p1 + dx_p2
    yd = y * radial + dy_p1 + dy_p2
    return DistortionTerms(r2, radial, dx_p1, dx_p2, dy_p1, dy_p2, xd, yd)


def distortion_jacobian(
    x: np.ndarray,
    y: np.ndarray,
    dist: np.ndarray,
    terms: DistortionTerms,
    with_dist: bool = True,
) -> DistortionJacobian:
    """Derivatives of the distorted coordinates by the point and by the coefficients.

    Args:
        x: (...,) normalized x.
        y: (...,) normalized y.
        dist: (..., 5) coefficients ``(k1, k2, p1, p2, k3)``, broadcastable to ``x``.
        terms: :func:`distortion_terms` of the same points and coefficients.
        with_dist: also return the derivatives by the coefficients.

    Returns:
        ``d(xd, yd)/d(x, y)`` (..., 2, 2) and ``d(xd, yd)/d(k1, k2, p1, p2, k3)`` (..., 2, 5).
    """
    k1, k2, p1, p2, k3 = (dist[..., i] for i in range(5))
    r2, radial = terms.r2, terms.radial
    r4 = r2 * r2
    dr = k1 + 2 * k2 * r2 + 3 * k3 * r4  # d radial / d r2
    d_xy = np.empty(np.shape(x) + (2, 2))
    d_xy[..., 0, 0] = radial + 2 * x * x * dr + 2 * p1 * y + 6 * p2 * x
    d_xy[..., 0, 1] = 2 * x * y * dr + 2 * p1 * x + 2 * p2 * y
    d_xy[..., 1, 0] = 2 * x * y * dr + 2 * p1 * x + 2 * p2 * y
    d_xy[..., 1, 1] = radial + 2 * y * y * dr + 6 * p1 * y + 2 * p2 * x
    if not with_dist:
        return DistortionJacobian(d_xy, None)
    d_dist = np.stack(
        [
            np.stack([x * r2, x * r4, 2 * x * y, r2 + 2 * x * x, x * r4 * r2], -1),
            np.stack([y * r2, y * r4, r2 + 2 * y * y, 2 * x * y, y * r4 * r2], -1),
        ],
        -2,
    )
    return DistortionJacobian(d_xy, d_dist)


def distort_normalized(xy: np.ndarray, dist: np.ndarray) -> np.ndarray:
    """Apply OpenCV distortion to normalized coordinates.

    Args:
        xy: (..., 2) normalized image coordinates (x/z, y/z).
        dist: (5,) coefficients ``(k1, k2, p1, p2, k3)``, or (..., 5) broadcastable to
            ``xy[..., 0]``.

    Returns:
        (..., 2) distorted normalized coordinates.
    """
    xy = check_last(xy, 2, "xy")
    t = distortion_terms(xy[..., 0], xy[..., 1], check_last(dist, 5, "dist"))
    return np.stack([t.xd, t.yd], axis=-1)


def undistort_normalized(xy_d: np.ndarray, dist: np.ndarray, iterations: int = 20) -> np.ndarray:
    """Invert OpenCV distortion for normalized coordinates (fixed point, then Newton).

    The fixed-point iterations stop once no point moves by more than ``1e-6``; Newton's
    quadratic convergence then reaches machine precision in two steps (it stops after a step
    under ``1e-9``: what remains is of the order of the step squared). A call on a few points
    costs about a hundred small array operations.

    Args:
        xy_d: (..., 2) distorted normalized coordinates.
        dist: (5,) coefficients, or (..., 5) broadcastable to ``xy_d[..., 0]`` (e.g. (C, 5)
            for points (..., C, 2) of C cameras).
        iterations: at most this many fixed-point iterations before the Newton polish.

    Returns:
        (..., 2) undistorted normalized coordinates.
    """
    xy_d = check_last(xy_d, 2, "xy_d")
    d = check_last(dist, 5, "dist")
    if not np.any(d):
        return xy_d.copy()
    xd, yd = xy_d[..., 0], xy_d[..., 1]
    x, y = xd, yd
    for _ in range(iterations):  # OpenCV's scheme: a good start for Newton
        t = distortion_terms(x, y, d)
        xn = (xd - (t.dx_p1 + t.dx_p2)) / t.radial
        yn = (yd - (t.dy_p1 + t.dy_p2)) / t.radial
        moved = _largest_change(xn - x, yn - y)
        x, y = xn, yn
        if moved <= _FIXED_POINT_TOL:
            break
    for _ in range(4):  # Newton polish to machine precision
        t = distortion_terms(x, y, d)
        rx, ry = t.xd - xd, t.yd - yd
        J = distortion_jacobian(x, y, d, t, with_dist=False).d_xy
        with np.errstate(divide="ignore", invalid="ignore"):
            det = J[..., 0, 0] * J[..., 1, 1] - J[..., 0, 1] * J[..., 1, 0]
            sx = (J[..., 1, 1] * rx - J[..., 0, 1] * ry) / det
            sy = (-J[..., 1, 0] * rx + J[..., 0, 0] * ry) / det
        x, y = x - sx, y - sy
        if _largest_change(sx, sy) <= _NEWTON_TOL:
            break
    return np.stack(np.broadcast_arrays(x, y), axis=-1)


_FIXED_POINT_TOL = 1e-6
_NEWTON_TOL = 1e-9


def _largest_change(dx: np.ndarray, dy: np.ndarray) -> float:
    """The largest finite ``|dx|`` or ``|dy|`` (0 when none is finite)."""
    a = np.abs(np.concatenate([np.ravel(dx), np.ravel(dy)]))
    return float(a.max(initial=0.0, where=np.isfinite(a)))
