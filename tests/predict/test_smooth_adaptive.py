"""The adaptive process noise keeps a brief fast oscillation; a lost keypoint is re-acquired."""

from __future__ import annotations

import numpy as np
import pytest

from freipose.predict.smooth import MISFIT_REJECTED, misfit_warning, smooth_arrays

T, FPS = 800, 25.0


def _bursts(seed: int = 0):
    """Slow motion on 3 keypoints; keypoint 0 oscillates at 5 Hz, 30 mm, 1 s of every 8 s."""
    rng = np.random.default_rng(seed)
    t = np.arange(T) / FPS
    slow = [20 * np.sin(2 * np.pi * 0.3 * t + a) + 10 * np.sin(2 * np.pi * 0.7 * t + 2 * a)
            for a in range(3)]  # fmt: skip
    truth = np.repeat(np.stack(slow, -1)[:, None], 3, axis=1)
    on = ((t % 8) >= 2) & ((t % 8) < 3)
    truth[:, 0, 2] += np.where(on, 30 * np.sin(2 * np.pi * 5 * t), 0.0)
    z = truth + rng.normal(size=truth.shape) * 3.0
    return t, on, truth, z, rng.uniform(0.3, 1.0, (T, 3))


def _amplitude(t: np.ndarray, on: np.ndarray, x: np.ndarray) -> float:
    """Mean 5 Hz amplitude over the first second of each burst."""
    starts = np.flatnonzero(np.diff(on.astype(int)) == 1) + 1
    c = np.exp(-2j * np.pi * 5 * t)
    return float(np.mean([abs((x[s : s + 25] * c[s : s + 25]).sum()) * 2 / 25 for s in starts]))


@pytest.fixture(scope="module")
def bursts():
    t, on, truth, z, conf = _bursts()
    dt = np.full(T, 1 / FPS)
    return t, on, truth, z, smooth_arrays(z, conf, dt), smooth_arrays(z, conf, dt, adaptive=False)


def test_oscillation_kept(bursts):
    t, on, truth, z, res, fixed = bursts
    assert _amplitude(t, on, truth[:, 0, 2]) == pytest.approx(30, rel=0.05)
    assert _amplitude(t, on, res.mean[:, 0, 2]) > 0.75 * 30
    assert _amplitude(t, on, fixed.mean[:, 0, 2]) < 0.3 * 30  # what one process noise does


def test_band_and_error_in_bursts(bursts):
    t, on, truth, z, res, fixed = bursts
    err = np.abs(res.mean - truth)
    assert (err[on, 0, 2] <= 2 * res.std[on, 0, 2]).mean() > 0.75
    assert (err <= 2 * res.std).mean() > 0.93
    raw = np.median(np.linalg.norm(z - truth, axis=-1))
    assert np.median(np.linalg.norm(res.mean - truth, axis=-1)) < 0.5 * raw
    # the keypoints that never move fast are smoothed (mostly) as before: the adaptive
    # process noise rises by chance in a few windows of their noise, not throughout
    assert (np.abs(res.mean[:, 1:] - fixed.mean[:, 1:]) > 0.5).mean() < 0.1
    slow = [
        np.median(np.linalg.norm(m[:, 1:] - truth[:, 1:], axis=-1)) for m in (res.mean, fixed.mean)
    ]
    assert slow[0] < 1.1 * slow[1]


def test_lost_keypoint_reacquired():
    t, _, truth, z, conf = _bursts(1)
    z = z.copy()
    z[400:, 1] += 200.0  # a jump the gate alone would reject for the rest of the recording
    res = smooth_arrays(z, conf, np.full(T, 1 / FPS), adaptive=False)
    assert res.rejected[:, 1].sum() < 10
    np.testing.assert_allclose(res.mean[420:, 1], truth[420:, 1] + 200.0, atol=6.0)


def test_misfit_warning_names_the_keypoints_the_model_leaves_out(bursts):
    t, on, truth, z, res, fixed = bursts
    names = ("burst", "slow a", "slow b")
    assert misfit_warning(res, names) is None  # the burst is followed, not left out
    assert misfit_warning(fixed, names) is None  # one process noise: damped, not left out
    lost = z.copy()
    spikes = np.arange(10, T - 10, 12)  # the network loses "slow a" in 8 % of the frames
    lost[spikes, 1] += np.array([80.0, -60.0, 70.0])
    out = smooth_arrays(lost, _bursts()[4], np.full(T, 1 / FPS))
    assert out.rejected[spikes, 1].mean() > 0.9
    rejected = out.rejected.mean(axis=0)
    assert rejected[1] > MISFIT_REJECTED > rejected[[0, 2]].max()
    warning = misfit_warning(out, names)
    assert warning is not None and "slow a" in warning and "burst" not in warning


def test_sudden_step_followed_not_left_out():
    """A paw's step (40 mm within 2 frames, then still) is movement, not an outlier."""
    t, _, truth, z, conf = _bursts(2)
    truth = truth.copy()
    truth[:, 2, 0] += np.clip((np.arange(T) - 400) / 2, 0, 1) * 40.0
    rng = np.random.default_rng(3)
    z = z.copy()
    z[:, 2] = truth[:, 2] + rng.normal(size=(T, 3)) * 0.3  # a precise keypoint
    res = smooth_arrays(z, conf, np.full(T, 1 / FPS))
    assert not res.rejected[395:410, 2].any()
    err = np.linalg.norm(res.mean[398:408, 2] - truth[398:408, 2], axis=-1)
    assert err.max() < 5.0  # the step is followed, not smoothed away


def test_running_quantiles_equal_numpys():
    """The windows' quantiles of the adaptive noise are NumPy's nanquantile, float for float."""
    import warnings

    from freipose.predict.smooth import _row_quantiles

    rng = np.random.default_rng(3)
    x = rng.normal(size=(400, 3, 9)) * 50
    x[rng.random(x.shape) < 0.4] = np.nan
    x[0, 0] = np.nan  # a row without values
    x[1, 0, 1:] = np.nan  # a row of one value
    qs = (0.5, 0.0, 0.1, 0.37, 0.9, 1.0)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # the row without values
        ref = np.nanquantile(x, list(qs), axis=-1)
    for a, b in zip(ref, _row_quantiles(x, qs), strict=True):
        assert np.array_equal(a, b, equal_nan=True)
