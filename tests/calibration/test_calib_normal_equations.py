"""The Levenberg-Marquardt solver's analytic Jacobians and normal-equation blocks against
finite differences and a dense J^T W J."""

from __future__ import annotations

import numpy as np

from freipose.calibration.bundle_problem import Observations, Problem, Segments, normal_equations
from freipose.geometry.transforms import rodrigues


def _problem(rng, C=3, F=5, P=6):
    """Random observations of P board points by C cameras in F frames; camera 1 never sees
    frame 2 and frame 4 is seen by nobody (empty pairs and an empty board pose)."""
    intr = np.column_stack([
        rng.uniform(500, 600, C), rng.uniform(500, 600, C), rng.uniform(300, 340, C),
        rng.uniform(220, 260, C), rng.normal(0, 0.05, (C, 5)),
    ])  # fmt: skip
    Rc = rodrigues(rng.normal(0, 0.2, (C, 3)))
    tc = np.column_stack([rng.normal(0, 50, (C, 2)), rng.uniform(800, 1000, C)])
    Rf = rodrigues(rng.normal(0, 0.3, (F, 3)))
    tf = rng.normal(0, 60, (F, 3))
    points = np.column_stack([rng.uniform(0, 200, (P, 2)), np.zeros(P)])
    cam, frame, point = [], [], []
    for c in range(C):
        for f in range(F - 1):
            if (c, f) == (1, 2):
                continue
            for p in rng.choice(P, size=rng.integers(3, P + 1), replace=False):
                cam.append(c)
                frame.append(f)
                point.append(points[p])
    n = len(cam)
    obs = Observations(
        np.array(cam), np.array(frame), np.array(point), rng.normal(320, 100, (n, 2))
    )
    order = rng.permutation(n)  # the problem sorts them itself
    return Problem(obs.subset(order), C, F), (intr, Rc, tc, Rf, tf)


def test_jacobians_match_finite_differences():
    rng = np.random.default_rng(0)
    prob, (intr, Rc, tc, Rf, tf) = _problem(rng)
    r0, cache = prob.residuals(intr, Rc, tc, Rf, tf)
    Jc, Jf = prob.jacobians(Rc, Rf, cache)
    h = 1e-6

    def camera_step(c, d):  # d (15,): intrinsics, left-multiplied rotation, translation
        i2, Rc2, tc2 = intr.copy(), Rc.copy(), tc.copy()
        i2[c] += d[:9]
        Rc2[c] = rodrigues(d[9:12]) @ Rc[c]
        tc2[c] += d[12:]
        return prob.residuals(i2, Rc2, tc2, Rf, tf)[0]

    def frame_step(f, d):  # d (6,): left-multiplied rotation, translation
        Rf2, tf2 = Rf.copy(), tf.copy()
        Rf2[f] = rodrigues(d[:3]) @ Rf[f]
        tf2[f] += d[3:]
        return prob.residuals(intr, Rc, tc, Rf2, tf2)[0]

    for J, owner, step in ((Jc, prob.obs.cam, camera_step), (Jf, prob.obs.frame, frame_step)):
        for i in np.unique(owner):
            m = owner == i
            for k in range(J.shape[2]):
                d = np.zeros(J.shape[2])
                d[k] = h
                np.testing.assert_allclose(
                    (step(i, d)[m] - r0[m]) / h,
                    J[m, :, k],
                    rtol=2e-4,
                    atol=2e-3 * max(1, abs(J[m, :, k]).max()),
                )


def test_normal_equations_match_dense_products():
    rng = np.random.default_rng(1)
    prob, (intr, Rc, tc, Rf, tf) = _problem(rng)
    r, cache = prob.residuals(intr, Rc, tc, Rf, tf)
    w = rng.uniform(0.2, 1.0, len(r))
    free = np.ones((prob.C, 15), bool)
    free[0, 9:] = False  # the gauge: camera 0's pose is fixed
    ne = normal_equations(prob, Rc, Rf, cache, r, w, free)
    Hcc, Hff, Hcf, gc, gf = ne.Hcc, ne.Hff, ne.Hcf, ne.gc, ne.gf
    Jc, Jf = prob.jacobians(Rc, Rf, cache)
    Jc = Jc * free[prob.obs.cam][:, None, :]
    C, F, N = prob.C, prob.F, len(r)
    J = np.zeros((2 * N, 15 * C + 6 * F))
    for n, (c, f) in enumerate(zip(prob.obs.cam, prob.obs.frame)):
        J[2 * n : 2 * n + 2, 15 * c : 15 * c + 15] = Jc[n]
        J[2 * n : 2 * n + 2, 15 * C + 6 * f : 15 * C + 6 * f + 6] = Jf[n]
    W = np.repeat(w, 2)
    H = J.T @ (W[:, None] * J)
    g = J.T @ (W * r.reshape(-1))
    for c in range(C):
        Hc = H[15 * c : 15 * c + 15, 15 * c : 15 * c + 15].copy()
        fixed = np.flatnonzero(~free[c])
        Hc[fixed, :] = 0
        Hc[:, fixed] = 0
        Hc[fixed, fixed] = 1.0
        np.testing.assert_allclose(Hcc[c], Hc, rtol=1e-10, atol=1e-8)
        np.testing.assert_allclose(gc[c], g[15 * c : 15 * c + 15], rtol=1e-10, atol=1e-8)
        for f in range(F):
            np.testing.assert_allclose(
                Hcf[c, f], H[15 * c : 15 * c + 15, 15 * C + 6 * f : 15 * C + 6 * f + 6],
                rtol=1e-10, atol=1e-8,
            )  # fmt: skip
    for f in range(F):
        blk = slice(15 * C + 6 * f, 15 * C + 6 * f + 6)
        np.testing.assert_allclose(Hff[f], H[blk, blk], rtol=1e-10, atol=1e-8)
        np.testing.assert_allclose(gf[f], g[blk], rtol=1e-10, atol=1e-8)
    assert not Hff[4].any() and not Hcf[1, 2].any()  # nobody sees frame 4; cam 1 not frame 2


def test_segments_sum_runs_of_sorted_keys():
    seg = Segments(np.array([0, 0, 2, 2, 2, 3]), 5)
    x = np.arange(12.0).reshape(6, 2)
    np.testing.assert_array_equal(seg(x), [[2, 4], [0, 0], [18, 21], [10, 11], [0, 0]])
    assert Segments(np.zeros(0, int), 3)(np.zeros((0, 2))).shape == (3, 2)
