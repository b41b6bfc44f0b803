"""Per-frame time series: gap filling, time derivatives and the short-time amplitude spectrum.

All functions work along axis 0 (time) and are vectorized over the other axes.
"""

from __future__ import annotations

import numpy as np

from freipose.errors import FreiPoseError


class SignalError(FreiPoseError):
    """A time series is too short or has the wrong shape; the message says why."""


def interpolate_gaps(x: np.ndarray, max_gap: int) -> tuple[np.ndarray, int]:
    """Linearly interpolate interior NaN runs of at most ``max_gap`` samples, per column.

    Args:
        x: (T, ...) array; every trailing index is an independent series.
        max_gap: longest run of NaN samples to fill (0 fills nothing).

    Returns:
        (filled copy of x, number of samples filled).
    """
    x = np.array(x, dtype=np.float64, copy=True)
    t = x.shape[0]
    if max_gap <= 0 or t < 3:
        return x, 0
    flat = x.reshape(t, -1)
    nan = np.isnan(flat)
    if not nan.any():
        return x, 0
    idx = np.arange(t)[:, None]
    prev = np.where(~nan, idx, -1)
    np.maximum.accumulate(prev, axis=0, out=prev)
    nxt = np.where(~nan, idx, t)
    nxt = np.minimum.accumulate(nxt[::-1], axis=0)[::-1]
    fill = nan & (prev >= 0) & (nxt < t) & (nxt - prev - 1 <= max_gap)
    if not fill.any():
        return x, 0
    rows, cols = np.nonzero(fill)
    p, n = prev[rows, cols], nxt[rows, cols]
    w = (rows - p) / (n - p)
    flat[rows, cols] = flat[p, cols] * (1 - w) + flat[n, cols] * w
    return x, int(len(rows))


def time_derivative(x: np.ndarray, fps: float) -> np.ndarray:
    """Central differences along time (axis 0) times fps: (T, ...) -> (T, ...)."""
    if x.shape[0] < 2:
        raise SignalError("need at least 2 frames for velocities")
    return np.gradient(x, axis=0) * fps


def stft_frequencies(window: int, fps: float) -> np.ndarray:
    """(window // 2 + 1,) frequencies in Hz of the STFT bins."""
    return np.arange(window // 2 + 1) * fps / window


def stft_amplitude(
    signals: np.ndarray, window: int = 64, chunk_frames: int = 16384, out: np.ndarray | None = None
) -> np.ndarray:
    """Per-frame short-time amplitude spectrum with a centred Hann window.

    A strided view of the (mirror-padded) signal, windowed and transformed by one batched
    real FFT (``scipy.fft.rfft``) per block of ``chunk_frames`` frames.

    Args:
        signals: (T, S) real signals, NaN allowed (a window touching NaN gives NaN).
        window: even window length in frames.
        chunk_frames: frames per block of the batched FFT (bounds the memory).
        out: optional (T, S, F) float32 array to fill.

    Returns:
        (T, S, F) float32 amplitudes, F = window // 2 + 1.
    """
    x = np.asarray(signals, dtype=np.float32)
    if x.ndim != 2:
        raise SignalError(f"signals must be (T, S), got {x.shape}")
    t, s = x.shape
    half = window // 2
    if t <= half:
        raise SignalError(
            f"recording too short for the STFT: {t} frames, need more than {half} "
            f"(half the {window}-frame window)"
        )
    import scipy.fft

    nf = half + 1
    win = (0.5 - 0.5 * np.cos(2 * np.pi * np.arange(window) / window)).astype(np.float32)
    scale = np.full(nf, 2.0 / win.sum(), dtype=np.float32)  # periodic Hann, amplitude scaling
    scale[0] = scale[-1] = 1.0 / win.sum()
    # Centred: frame i uses padded samples i .. i + window - 1 = original i - half .. i + half - 1.
    xp = np.pad(x, ((half, half - 1), (0, 0)), mode="reflect")
    if out is None:
        out = np.empty((t, s, nf), dtype=np.float32)
    for a in range(0, t, chunk_frames):
        b = min(t, a + chunk_frames)
        view = np.lib.stride_tricks.sliding_window_view(xp[a : b + window - 1], window, axis=0)
        spec = scipy.fft.rfft(view * win, axis=-1)  # (b-a, S, F) complex64, batched FFT
        np.multiply(np.abs(spec), scale, out=out[a:b])
    return out
