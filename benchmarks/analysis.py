"""Benchmark: behavioral variables of one hour at 100 fps (360,000 frames, 912 variables).

Target (issue 9): under a minute on 2 cores. Prints the time of ``compute_variables`` and,
as a baseline measured in the same run, the time of a plain per-frame loop over the STFT
(``numpy.fft.rfft`` of each 64-frame window in a Python loop) on a slice,
extrapolated to the full length.

    python benchmarks/analysis.py [--minutes 60] [--fps 100] [--threads 2]
"""

from __future__ import annotations

import argparse
import os
import time

from _results import write_result


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--minutes", type=float, default=60.0)
    ap.add_argument("--fps", type=float, default=100.0)
    ap.add_argument("--threads", type=int, default=2, help="BLAS threads (cores)")
    ap.add_argument("--write", action="store_true", help="also time writing VARS.h5")
    args = ap.parse_args()
    for var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
        os.environ[var] = str(args.threads)

    import numpy as np

    from freipose.analysis.floor import FloorPlane
    from freipose.analysis.simulate import simulate_rat, stimulation_windows
    from freipose.analysis.variables import compute_variables
    from freipose.skeleton import load_skeleton

    dur = args.minutes * 60
    t0 = time.perf_counter()
    data = simulate_rat(dur, args.fps, stimulation_windows(dur, 10, 50, 5), seed=0)
    poses = data.poses.copy()
    rng = np.random.default_rng(0)
    miss = rng.random(poses.shape[:2]) < 0.01  # 1 % missing keypoints, mostly short gaps
    poses[miss] = np.nan
    print(f"simulated {len(poses):,} frames in {time.perf_counter() - t0:.1f} s")

    skel = load_skeleton("rat")
    floor = FloorPlane.world([0, 0, 1])
    t0, c0 = time.perf_counter(), time.process_time()
    var = compute_variables(poses, data.frame_index, args.fps, skel, floor)
    dt, dc = time.perf_counter() - t0, time.process_time() - c0
    n, v = var.values.shape
    print(
        f"compute_variables: {n:,} frames x {v} variables in {dt:.2f} s wall, {dc:.2f} s CPU "
        f"({n / dt / 1e3:.0f} k frames/s, {var.values.nbytes / 2**30:.2f} GiB float32; "
        f"{args.threads} BLAS threads); target < 60 s: {'PASS' if dt < 60 else 'FAIL'}"
    )

    # Baseline: the naive per-frame STFT loop on 24 signals, on a slice, extrapolated.
    sig = np.nan_to_num(var.values[:, var.kinds.index("origin_dist") :][:, :12])
    sig = np.concatenate([sig, sig], axis=1)
    m = min(n, 5000)
    win = np.hanning(64)
    c0 = time.process_time()
    for i in range(32, 32 + m - 64):
        np.abs(np.fft.rfft(sig[i - 32 : i + 32].T * win, axis=1))
    naive = (time.process_time() - c0) / (m - 64) * n
    from freipose.analysis.signals import stft_amplitude

    c0 = time.process_time()
    stft_amplitude(sig)
    fast = time.process_time() - c0
    print(
        f"STFT of 24 signals (CPU time): batched strided FFT {fast:.2f} s vs per-frame rfft loop "
        f"{naive:.1f} s (extrapolated from {m} frames): {naive / fast:.1f}x faster"
    )
    figures = {
        "frames": n,
        "variables": v,
        "compute_variables_wall_s": dt,
        "compute_variables_cpu_s": dc,
        "stft_batched_cpu_s": fast,
        "stft_loop_cpu_s_extrapolated": naive,
        "stft_speedup": naive / fast,
    }
    if args.write:
        import tempfile
        from pathlib import Path

        from freipose.analysis.io import write_variables_h5

        with tempfile.TemporaryDirectory() as d:
            t0 = time.perf_counter()
            write_variables_h5(var, Path(d) / "bench.vars.h5")
            figures["write_vars_h5_s"] = time.perf_counter() - t0
            print(f"write VARS.h5: {figures['write_vars_h5_s']:.1f} s")
    extra = {"minutes": args.minutes, "fps": args.fps, "threads": args.threads, "seed": 0}
    write_result("analysis", figures, extra=extra)


if __name__ == "__main__":
    main()
