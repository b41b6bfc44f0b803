// Camera geometry of the labeling page, the same model as freipose.geometry (NumPy):
// world -> camera x_c = R X + t (mm), OpenCV distortion (k1, k2, p1, p2, k3), pixel origin
// at the centre of the top-left pixel. A camera is {K, dist, R, t, size} as /api/config
// sends it. The tests compare these numbers with the Python geometry.
"use strict";

const FPGeom = (() => {
  const EPS_DEPTH = 1e-9;

  function terms(x, y, d) {
    const [k1, k2, p1, p2, k3] = d;
    const r2 = x * x + y * y;
    const radial = 1 + r2 * (k1 + r2 * (k2 + r2 * k3));
    const dxp = 2 * p1 * x * y + p2 * (r2 + 2 * x * x);
    const dyp = p1 * (r2 + 2 * y * y) + 2 * p2 * x * y;
    return { r2, radial, dxp, dyp, xd: x * radial + dxp, yd: y * radial + dyp };
  }

  function distort(x, y, d) {
    const t = terms(x, y, d);
    return [t.xd, t.yd];
  }

  // Inverse of distort: OpenCV's fixed point (20 steps), then 4 Newton steps.
  function undistort(xd, yd, d) {
    if (d.every((v) => v === 0)) return [xd, yd];
    let x = xd, y = yd;
    for (let i = 0; i < 20; i++) {
      const t = terms(x, y, d);
      x = (xd - t.dxp) / t.radial;
      y = (yd - t.dyp) / t.radial;
    }
    const [k1, k2, p1, p2, k3] = d;
    for (let i = 0; i < 4; i++) {
      const t = terms(x, y, d);
      const rx = t.xd - xd, ry = t.yd - yd;
      const dr = k1 + 2 * k2 * t.r2 + 3 * k3 * t.r2 * t.r2;
      const a = t.radial + 2 * x * x * dr + 2 * p1 * y + 6 * p2 * x;
      const b = 2 * x * y * dr + 2 * p1 * x + 2 * p2 * y;
      const e = t.radial + 2 * y * y * dr + 6 * p1 * y + 2 * p2 * x;
      const det = a * e - b * b;
      x -= (e * rx - b * ry) / det;
      y -= (-b * rx + a * ry) / det;
    }
    return [x, y];
  }

  function toCamera(cam, X) {
    const R = cam.R, t = cam.t;
    return [0, 1, 2].map((i) => R[i][0] * X[0] + R[i][1] * X[1] + R[i][2] * X[2] + t[i]);
  }

  // World point (mm) -> pixel [u, v] with distortion; null behind the camera.
  function project(cam, X) {
    const c = toCamera(cam, X);
    if (!(c[2] > EPS_DEPTH)) return null;
    const [xd, yd] = distort(c[0] / c[2], c[1] / c[2], cam.dist);
    const K = cam.K;
    return [K[0][0] * xd + K[0][1] * yd + K[0][2], K[1][1] * yd + K[1][2]];
  }

  function center(cam) {
    const R = cam.R, t = cam.t;
    return [0, 1, 2].map((j) => -(R[0][j] * t[0] + R[1][j] * t[1] + R[2][j] * t[2]));
  }

  // Pixel -> world ray {origin (camera centre, mm), direction (unit)}.
  function pixelToRay(cam, u, v) {
    const K = cam.K;
    const yn = (v - K[1][2]) / K[1][1];
    const xn = (u - K[0][2] - K[0][1] * yn) / K[0][0];
    const [x, y] = undistort(xn, yn, cam.dist);
    const R = cam.R;
    const d = [0, 1, 2].map((j) => R[0][j] * x + R[1][j] * y + R[2][j]);
    const n = Math.hypot(d[0], d[1], d[2]);
    return { origin: center(cam), direction: d.map((c) => c / n) };
  }

  // Distances (mm) along a ray at which to sample epipolar curves: geometric steps from
  // `near` to `far`.
  function depths(near, far, n) {
    const out = [];
    for (let i = 0; i < n; i++) out.push(near * Math.pow(far / near, i / (n - 1)));
    return out;
  }

  // The epipolar curve in camera B of pixel (u, v) of camera A: the ray's points at the
  // given distances projected into B (null where behind B).
  function epipolar(camA, u, v, camB, dists) {
    const ray = pixelToRay(camA, u, v);
    return dists.map((s) =>
      project(camB, ray.origin.map((o, i) => o + s * ray.direction[i]))
    );
  }

  // Linear least-squares triangulation of pixels uvs[n] seen by cams[n] (n >= 2), with the
  // lens distortion removed first; null when the views do not fix a point.
  function triangulate(cams, uvs) {
    const A = [[0, 0, 0], [0, 0, 0], [0, 0, 0]], b = [0, 0, 0];
    cams.forEach((cam, n) => {
      const K = cam.K, R = cam.R, t = cam.t;
      const yn = (uvs[n][1] - K[1][2]) / K[1][1];
      const xn = (uvs[n][0] - K[0][2] - K[0][1] * yn) / K[0][0];
      const xy = undistort(xn, yn, cam.dist);
      for (let r = 0; r < 2; r++) { // xy[r] (R[2] X + t[2]) = R[r] X + t[r]
        const row = [0, 1, 2].map((j) => xy[r] * R[2][j] - R[r][j]);
        const rhs = t[r] - xy[r] * t[2];
        for (let i = 0; i < 3; i++) {
          b[i] += row[i] * rhs;
          for (let j = 0; j < 3; j++) A[i][j] += row[i] * row[j];
        }
      }
    });
    const det = (m) => m[0][0] * (m[1][1] * m[2][2] - m[1][2] * m[2][1]) -
      m[0][1] * (m[1][0] * m[2][2] - m[1][2] * m[2][0]) +
      m[0][2] * (m[1][0] * m[2][1] - m[1][1] * m[2][0]);
    const d = det(A);
    if (!(Math.abs(d) > 1e-12)) return null;
    return [0, 1, 2].map((c) => det(A.map((row, i) => row.map((v, j) => (j === c ? b[i] : v)))) / d);
  }

  return { distort, undistort, project, center, pixelToRay, depths, epipolar, triangulate };
})();
