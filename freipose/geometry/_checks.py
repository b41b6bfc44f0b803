"""Input checks shared by the NumPy geometry modules."""

from __future__ import annotations

import numpy as np


def check_last(arr: np.ndarray, n: int, what: str) -> np.ndarray:
    """``arr`` as a float64 array whose last axis has length ``n``.

    Args:
        arr: the input, any array-like.
        n: the required length of the last axis.
        what: the input's name for the message.

    Returns:
        (..., n) float64 array (no copy when ``arr`` already is one).

    Raises:
        ValueError: ``arr`` is a scalar or its last axis has another length.
    """
    a = np.asarray(arr, dtype=np.float64)
    if a.ndim == 0 or a.shape[-1] != n:
        raise ValueError(f"{what} must have shape (..., {n}), got shape {a.shape}")
    return a
