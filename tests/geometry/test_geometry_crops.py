"""label_centers: the mean of each instant's labeled 3D points."""

from __future__ import annotations

import numpy as np

from freipose.geometry.crops import label_centers


def test_label_centers_mean_of_the_finite_and_masked_points() -> None:
    p = np.array(
        [
            [[0.0, 0.0, 0.0], [2.0, 4.0, 6.0], [np.nan, 1.0, 1.0]],
            [[np.nan] * 3, [np.nan] * 3, [np.nan] * 3],
            [[1.0, 1.0, 1.0], [3.0, 3.0, 3.0], [5.0, 5.0, 5.0]],
        ]
    )
    c = label_centers(p)
    np.testing.assert_array_equal(c[0], [1.0, 2.0, 3.0])  # the NaN point is left out
    assert np.isnan(c[1]).all()  # no labeled point: NaN, no warning
    np.testing.assert_array_equal(c[2], [3.0, 3.0, 3.0])
    mask = np.array([[True, False, True], [True, True, True], [False, True, True]])
    cm = label_centers(p, mask)
    np.testing.assert_array_equal(cm[0], [0.0, 0.0, 0.0])
    np.testing.assert_array_equal(cm[2], [4.0, 4.0, 4.0])
    np.testing.assert_array_equal(label_centers(p[2]), [3.0, 3.0, 3.0])  # one instant (K, 3)
