"""Compiled hot loop of the batched Levenberg-Marquardt (numba), and the Monte-Carlo's per-trial scores.

Each problem (one Monte-Carlo trial, or one calibration) is solved to
convergence inside compiled code, with no Python per iteration. A trial
step is judged by one pass over the points that computes only the
residuals. Where a step is accepted and the solve goes on, a second pass
writes the weighted Jacobian, one contiguous row per parameter (u of every
point, then v), into a workspace reused across problems. The normal
equations J^T W J, J^T W r of the free parameters are then dot products of
those rows, solved by Cholesky. Problems are independent and run in
parallel (``prange``, blocks of BLOCK problems) over numba's threads.
``monte_carlo_trials`` also scores each trial against the reference camera
in the same pass: projection errors, and the ground rays of
``core.camera.intersect_plane_z``. The algebra is the same as
``core.camera.project_batch_jacobians`` and ``core.camera.project_batch``
(the tests check they agree); conventions are in docs/conventions.md.
"""

from __future__ import annotations

import os
from collections.abc import Callable

# numba's OpenMP threads spin (GNU libgomp's default) for milliseconds after every parallel
# call before they sleep. The spinning thread burns a core while the caller goes on in
# Python: on the paper's grid a 2-trial Monte-Carlo cost 7.6 ms of CPU with 2 threads against
# 1.2 ms passive (22.7 ms against 1.2 ms of wall time on a busy 2-core machine, where the
# spinner competes with the caller), ~12 us of every trial at k = 500. Passive waiting
# changes no number. Read when libgomp loads, at the first parallel call (after this import);
# a value the user set stands.
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

import numpy as np  # noqa: E402
from numba import njit, prange  # noqa: E402

LOSS_CODES = {"linear": 0, "huber": 1, "cauchy": 2}


@njit(cache=True, fastmath=True, nogil=True)
def _weight(sq: float, loss: int, scale: float) -> float:
    if loss == 0:
        return 1.0
    r = np.sqrt(sq) / scale
    if loss == 1:
        return 1.0 if r <= 1.0 else 1.0 / max(r, 1e-12)
    return 1.0 / (1.0 + r * r)


@njit(cache=True, fastmath=True, nogil=True)
def _squared_residuals(
    intr: np.ndarray,  # (4,)
    dist: np.ndarray,  # (5,)
    R: np.ndarray,  # (3, 3)
    t: np.ndarray,  # (3,)
    X: np.ndarray,  # (N, 3)
    y: np.ndarray,  # (N, 2)
    sq: np.ndarray,  # (N,) out
) -> None:
    """Squared reprojection residual of every point: all a trial step needs to be judged."""
    fx, fy, cx, cy = intr[0], intr[1], intr[2], intr[3]
    k1, k2, p1, p2, k3 = dist[0], dist[1], dist[2], dist[3], dist[4]
    for n in range(y.shape[0]):
        X0, X1, X2 = X[n, 0], X[n, 1], X[n, 2]
        iz = 1.0 / (R[2, 0] * X0 + R[2, 1] * X1 + R[2, 2] * X2 + t[2])
        xn = (R[0, 0] * X0 + R[0, 1] * X1 + R[0, 2] * X2 + t[0]) * iz
        yn = (R[1, 0] * X0 + R[1, 1] * X1 + R[1, 2] * X2 + t[1]) * iz
        r2 = xn * xn + yn * yn
        radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
        xy2 = 2.0 * xn * yn
        ru = y[n, 0] - (fx * (xn * radial + p1 * xy2 + p2 * (r2 + 2.0 * xn * xn)) + cx)
        rv = y[n, 1] - (fy * (yn * radial + p1 * (r2 + 2.0 * yn * yn) + p2 * xy2) + cy)
        sq[n] = ru * ru + rv * rv


@njit(cache=True, fastmath=True, nogil=True)
def _jacobian_rows(
    intr: np.ndarray,  # (4,)
    dist: np.ndarray,  # (5,)
    R: np.ndarray,  # (3, 3)
    t: np.ndarray,  # (3,)
    X: np.ndarray,  # (N, 3)
    y: np.ndarray,  # (N, 2)
    w: np.ndarray,  # (N,)
    fx_col: int,
    aspect: float,
    J: np.ndarray,  # (15, 2N) out: sqrt(w)-weighted Jacobian, row p = parameter p (u of point n at n, v at N + n)
    r: np.ndarray,  # (2N,) out: sqrt(w)-weighted residuals, the same layout
    sq: np.ndarray,  # (N,) out: unweighted squared residuals
) -> None:
    """The weighted Jacobian of one problem for all 15 parameters, one contiguous row per parameter.

    Rows are written at fixed indices (no selection inside the point loop, so
    it vectorises); the free parameters are picked by row when the products
    are formed. With a tied aspect ratio (``fx_col`` >= 0) row 0 becomes
    d/dfx + aspect * d/dfy.
    """
    N = y.shape[0]
    fx, fy, cx, cy = intr[0], intr[1], intr[2], intr[3]
    k1, k2, p1, p2, k3 = dist[0], dist[1], dist[2], dist[3], dist[4]
    for n in range(N):
        X0, X1, X2 = X[n, 0], X[n, 1], X[n, 2]
        ax = R[0, 0] * X0 + R[0, 1] * X1 + R[0, 2] * X2
        ay = R[1, 0] * X0 + R[1, 1] * X1 + R[1, 2] * X2
        az = R[2, 0] * X0 + R[2, 1] * X1 + R[2, 2] * X2
        iz = 1.0 / (az + t[2])
        xn = (ax + t[0]) * iz
        yn = (ay + t[1]) * iz
        r2 = xn * xn + yn * yn
        r4 = r2 * r2
        radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
        xy2 = 2.0 * xn * yn
        xd = xn * radial + p1 * xy2 + p2 * (r2 + 2.0 * xn * xn)
        yd = yn * radial + p1 * (r2 + 2.0 * yn * yn) + p2 * xy2
        ru = y[n, 0] - (fx * xd + cx)
        rv = y[n, 1] - (fy * yd + cy)
        sq[n] = ru * ru + rv * rv
        sw = np.sqrt(w[n])
        r[n] = sw * ru
        r[N + n] = sw * rv
        drad = k1 + r2 * (2.0 * k2 + 3.0 * k3 * r2)
        dxd_dy = xy2 * drad + 2.0 * p1 * xn + 2.0 * p2 * yn
        a00 = fx * (radial + 2.0 * xn * xn * drad + 2.0 * p1 * yn + 6.0 * p2 * xn) * iz
        a01 = fx * dxd_dy * iz
        a10 = fy * dxd_dy * iz
        a11 = fy * (radial + 2.0 * yn * yn * drad + 6.0 * p1 * yn + 2.0 * p2 * xn) * iz
        gu2 = -(a00 * xn + a01 * yn)
        gv2 = -(a10 * xn + a11 * yn)
        J[0, n] = sw * xd
        J[1, n] = 0.0
        J[2, n] = sw
        J[3, n] = 0.0
        J[4, n] = sw * fx * xn * r2
        J[5, n] = sw * fx * xn * r4
        J[6, n] = sw * fx * xy2
        J[7, n] = sw * fx * (r2 + 2.0 * xn * xn)
        J[8, n] = sw * fx * xn * r4 * r2
        J[9, n] = sw * (ay * gu2 - az * a01)
        J[10, n] = sw * (az * a00 - ax * gu2)
        J[11, n] = sw * (ax * a01 - ay * a00)
        J[12, n] = sw * a00
        J[13, n] = sw * a01
        J[14, n] = sw * gu2
        J[0, N + n] = 0.0
        J[1, N + n] = sw * yd
        J[2, N + n] = 0.0
        J[3, N + n] = sw
        J[4, N + n] = sw * fy * yn * r2
        J[5, N + n] = sw * fy * yn * r4
        J[6, N + n] = sw * fy * (r2 + 2.0 * yn * yn)
        J[7, N + n] = sw * fy * xy2
        J[8, N + n] = sw * fy * yn * r4 * r2
        J[9, N + n] = sw * (ay * gv2 - az * a11)
        J[10, N + n] = sw * (az * a10 - ax * gv2)
        J[11, N + n] = sw * (ax * a11 - ay * a10)
        J[12, N + n] = sw * a10
        J[13, N + n] = sw * a11
        J[14, N + n] = sw * gv2
    if fx_col >= 0:
        for c in range(2 * N):
            J[0, c] += aspect * J[1, c]


@njit(cache=True, fastmath=True, nogil=True)
def _normal_from_rows(J: np.ndarray, r: np.ndarray, sel: np.ndarray, JtJ: np.ndarray, g: np.ndarray) -> None:
    """J^T J (m, m) and J^T r (m,) of the free parameters sel (m,) from the rows of J (15, 2N)."""
    m = sel.shape[0]
    n2 = J.shape[1]
    for a in range(m):
        ja = J[sel[a]]
        s = 0.0
        for c in range(n2):
            s += ja[c] * r[c]
        g[a] = s
        for b in range(a, m):
            jb = J[sel[b]]
            s = 0.0
            for c in range(n2):
                s += ja[c] * jb[c]
            JtJ[a, b] = s
            JtJ[b, a] = s


@njit(cache=True, fastmath=True, nogil=True)
def _accumulate(
    intr: np.ndarray,  # (4,)
    dist: np.ndarray,  # (5,)
    R: np.ndarray,  # (3, 3)
    t: np.ndarray,  # (3,)
    X: np.ndarray,  # (N, 3)
    y: np.ndarray,  # (N, 2)
    w: np.ndarray,  # (N,)
    sel: np.ndarray,  # (m,)
    fx_col: int,
    aspect: float,
    JtJ: np.ndarray,  # (m, m) out
    g: np.ndarray,  # (m,) out
    sq: np.ndarray,  # (N,) out
) -> None:
    """Normal equations of one problem at one parameter value (allocates its Jacobian; the solver reuses one)."""
    N = y.shape[0]
    J = np.empty((15, 2 * N))
    r = np.empty(2 * N)
    _jacobian_rows(intr, dist, R, t, X, y, w, fx_col, aspect, J, r, sq)
    _normal_from_rows(J, r, sel, JtJ, g)


@njit(cache=True, fastmath=True, nogil=True)
def _cholesky_solve(H: np.ndarray, b: np.ndarray, L: np.ndarray, x: np.ndarray) -> bool:
    """Solve H x = b for symmetric positive definite H (m, m) by Cholesky; False if H is not positive definite."""
    m = H.shape[0]
    for j in range(m):
        s = H[j, j]
        for k in range(j):
            s -= L[j, k] * L[j, k]
        if not (s > 0.0) or not np.isfinite(s):
            return False
        d = np.sqrt(s)
        L[j, j] = d
        for i in range(j + 1, m):
            s = H[i, j]
            for k in range(j):
                s -= L[i, k] * L[j, k]
            L[i, j] = s / d
    for i in range(m):
        s = b[i]
        for k in range(i):
            s -= L[i, k] * x[k]
        x[i] = s / L[i, i]
    for i in range(m - 1, -1, -1):
        s = x[i]
        for k in range(i + 1, m):
            s -= L[k, i] * x[k]
        x[i] = s / L[i, i]
    return True


@njit(cache=True, fastmath=True, nogil=True)
def _rodrigues(w0: float, w1: float, w2: float, out: np.ndarray) -> None:
    theta2 = w0 * w0 + w1 * w1 + w2 * w2
    if theta2 < 1e-16:
        a = 1.0 - theta2 / 6.0
        b = 0.5 - theta2 / 24.0
    else:
        theta = np.sqrt(theta2)
        a = np.sin(theta) / theta
        b = (1.0 - np.cos(theta)) / theta2
    out[0, 0] = 1.0 - b * (w1 * w1 + w2 * w2)
    out[0, 1] = -a * w2 + b * w0 * w1
    out[0, 2] = a * w1 + b * w0 * w2
    out[1, 0] = a * w2 + b * w0 * w1
    out[1, 1] = 1.0 - b * (w0 * w0 + w2 * w2)
    out[1, 2] = -a * w0 + b * w1 * w2
    out[2, 0] = -a * w1 + b * w0 * w2
    out[2, 1] = a * w0 + b * w1 * w2
    out[2, 2] = 1.0 - b * (w0 * w0 + w1 * w1)


@njit(cache=True, fastmath=True, nogil=True)
def _cost(w: np.ndarray, sq: np.ndarray) -> float:
    c = 0.0
    for n in range(sq.shape[0]):
        c += w[n] * sq[n]
    return c


@njit(cache=True, fastmath=True, nogil=True)
def _solve_one(
    intr: np.ndarray, dist: np.ndarray, R: np.ndarray, t: np.ndarray,
    X: np.ndarray, y: np.ndarray, A: np.ndarray, sel: np.ndarray, fx_col: int, aspect: float,
    max_iterations: int, tolerance: float, loss: int, scale: float, damping: float,
    J: np.ndarray, r: np.ndarray, w: np.ndarray, sq: np.ndarray, sq_t: np.ndarray,
    JtJ: np.ndarray, g: np.ndarray, H: np.ndarray, L: np.ndarray, delta: np.ndarray,
    intr_t: np.ndarray, dist_t: np.ndarray, R_t: np.ndarray, t_t: np.ndarray, dR: np.ndarray, full: np.ndarray,
) -> tuple[float, int]:
    """Levenberg-Marquardt for one problem, in place on intr, dist, R, t; returns (cost, iterations).

    The arrays after ``damping`` are workspace (J (15, 2N), r (2N,), w, sq, sq_t (N,), JtJ, H, L (m, m),
    g, delta (m,), intr_t (4,), dist_t (5,), R_t, dR (3, 3), t_t (3,), full (15,)), reused across
    problems. A trial step is judged on its residuals alone; the Jacobian is formed only where a
    step is accepted and the solve goes on.
    """
    N = y.shape[0]
    m = sel.shape[0]
    for n in range(N):
        w[n] = 1.0
    _jacobian_rows(intr, dist, R, t, X, y, w, fx_col, aspect, J, r, sq)
    if loss != 0:
        for n in range(N):
            w[n] = _weight(sq[n], loss, scale)
        _jacobian_rows(intr, dist, R, t, X, y, w, fx_col, aspect, J, r, sq)
    _normal_from_rows(J, r, sel, JtJ, g)
    cost = _cost(w, sq)
    lam = damping
    fails = 0
    it = 0
    for it in range(1, max_iterations + 1):
        for a in range(m):
            for b in range(m):
                H[a, b] = JtJ[a, b]
            H[a, a] += lam * max(JtJ[a, a], 1e-12)
        cost_t = np.inf
        if _cholesky_solve(H, g, L, delta):
            for i in range(15):
                s = 0.0
                for a in range(m):
                    s += A[i, a] * delta[a]
                full[i] = s
            for i in range(4):
                intr_t[i] = intr[i] + full[i]
            for i in range(5):
                dist_t[i] = dist[i] + full[4 + i]
            _rodrigues(full[9], full[10], full[11], dR)
            for i in range(3):
                t_t[i] = t[i] + full[12 + i]
                for j in range(3):
                    R_t[i, j] = dR[i, 0] * R[0, j] + dR[i, 1] * R[1, j] + dR[i, 2] * R[2, j]
            _squared_residuals(intr_t, dist_t, R_t, t_t, X, y, sq_t)
            # judged with the weights the step was computed with, so reweighting cannot fake progress
            cost_t = _cost(w, sq_t)
        if cost_t < cost and np.isfinite(cost_t):
            rel = (cost - cost_t) / max(cost, 1e-300)
            intr[:] = intr_t
            dist[:] = dist_t
            R[:, :] = R_t
            t[:] = t_t
            sq[:] = sq_t
            cost = cost_t
            lam = max(lam / 10.0, 1e-9)
            fails = 0
            if rel < tolerance or cost <= 1e-24:
                break
            if loss != 0:
                for n in range(N):
                    w[n] = _weight(sq[n], loss, scale)
            _jacobian_rows(intr, dist, R, t, X, y, w, fx_col, aspect, J, r, sq)
            _normal_from_rows(J, r, sel, JtJ, g)
            if loss != 0:
                cost = _cost(w, sq)
        else:
            lam *= 10.0
            fails += 1
            # at a minimum, round-off makes every step fail: a few failures in a row means converged
            if fails >= 4 or lam > 1e10:
                break
    total = 0.0
    for n in range(N):
        total += sq[n]
    return total, it


@njit(cache=True, nogil=True)
def _project_into(intr: np.ndarray, dist: np.ndarray, R: np.ndarray, t: np.ndarray, X0: float, X1: float, X2: float) -> tuple[float, float]:
    """Pixel (u, v) of one world point (the algebra of ``core.camera.project_batch``)."""
    iz = 1.0 / (R[2, 0] * X0 + R[2, 1] * X1 + R[2, 2] * X2 + t[2])
    xn = (R[0, 0] * X0 + R[0, 1] * X1 + R[0, 2] * X2 + t[0]) * iz
    yn = (R[1, 0] * X0 + R[1, 1] * X1 + R[1, 2] * X2 + t[1]) * iz
    k1, k2, p1, p2, k3 = dist[0], dist[1], dist[2], dist[3], dist[4]
    r2 = xn * xn + yn * yn
    radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
    xy = xn * yn
    xd = xn * radial + 2.0 * p1 * xy + p2 * (r2 + 2.0 * xn * xn)
    yd = yn * radial + p1 * (r2 + 2.0 * yn * yn) + 2.0 * p2 * xy
    return intr[0] * xd + intr[2], intr[1] * yd + intr[3]


@njit(cache=True, nogil=True)
def _undistort(xd: float, yd: float, dist: np.ndarray, iterations: int) -> tuple[float, float]:
    """Undistorted normalised (x, y) by Newton's method (``core.camera.undistort_normalised`` for one point)."""
    k1, k2, p1, p2, k3 = dist[0], dist[1], dist[2], dist[3], dist[4]
    x, y = xd, yd
    for _ in range(iterations):
        r2 = x * x + y * y
        radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
        xy = x * y
        ex = x * radial + 2.0 * p1 * xy + p2 * (r2 + 2.0 * x * x) - xd
        ey = y * radial + p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * xy - yd
        drad = k1 + r2 * (2.0 * k2 + 3.0 * k3 * r2)
        a = radial + 2.0 * x * x * drad + 2.0 * p1 * y + 6.0 * p2 * x
        b = 2.0 * x * y * drad + 2.0 * p1 * x + 2.0 * p2 * y
        d = radial + 2.0 * y * y * drad + 6.0 * p1 * y + 2.0 * p2 * x
        det = a * d - b * b
        if np.abs(det) < 1e-12:
            det = 1e-12
        x, y = x - (d * ex - b * ey) / det, y - (a * ey - b * ex) / det
    return x, y


@njit(cache=True, nogil=True)
def _intersect_into(intr: np.ndarray, dist: np.ndarray, R: np.ndarray, t: np.ndarray, uv: np.ndarray, z_plane: float, out: np.ndarray) -> None:
    """World points out (P, 3) where the rays of pixels uv (P, 2) meet the plane z = z_plane; NaN where they miss."""
    c0 = -(R[0, 0] * t[0] + R[1, 0] * t[1] + R[2, 0] * t[2])
    c1 = -(R[0, 1] * t[0] + R[1, 1] * t[1] + R[2, 1] * t[2])
    c2 = -(R[0, 2] * t[0] + R[1, 2] * t[1] + R[2, 2] * t[2])
    for p in range(uv.shape[0]):
        x, y = _undistort((uv[p, 0] - intr[2]) / intr[0], (uv[p, 1] - intr[3]) / intr[1], dist, 20)
        d0 = R[0, 0] * x + R[1, 0] * y + R[2, 0]
        d1 = R[0, 1] * x + R[1, 1] * y + R[2, 1]
        d2 = R[0, 2] * x + R[1, 2] * y + R[2, 2]
        norm = np.sqrt(d0 * d0 + d1 * d1 + d2 * d2)
        d0, d1, d2 = d0 / norm, d1 / norm, d2 / norm
        s = (z_plane - c2) / d2
        if not s > 0:
            s = np.nan
        out[p, 0] = c0 + s * d0
        out[p, 1] = c1 + s * d1
        out[p, 2] = c2 + s * d2


@njit(cache=True, nogil=True)
def _rms_projection_difference(intr: np.ndarray, dist: np.ndarray, R: np.ndarray, t: np.ndarray, X: np.ndarray, uv_ref: np.ndarray) -> float:
    """RMS over points X (M, 3) of the pixel distance between this camera's projection and uv_ref (M, 2); NaN for M = 0."""
    if X.shape[0] == 0:
        return np.nan
    s = 0.0
    for n in range(X.shape[0]):
        u, v = _project_into(intr, dist, R, t, X[n, 0], X[n, 1], X[n, 2])
        du, dv = u - uv_ref[n, 0], v - uv_ref[n, 1]
        s += du * du + dv * dv
    return np.sqrt(s / X.shape[0])


@njit(cache=True, nogil=True)
def intersect_plane_z(
    intr: np.ndarray,  # (K, 4)
    dist: np.ndarray,  # (K, 5)
    R: np.ndarray,  # (K, 3, 3)
    t: np.ndarray,  # (K, 3)
    uv: np.ndarray,  # (P, 2) pixels, the same for every camera
    z_plane: float,
    out: np.ndarray,  # (K, P, 3) out: world metres, NaN where a ray misses the plane
) -> None:
    """``core.camera.intersect_plane_z`` compiled, for pixels shared by K cameras."""
    for k in range(R.shape[0]):
        _intersect_into(intr[k], dist[k], R[k], t[k], uv, z_plane, out[k])


# Problems solved one after another by a thread, sharing one workspace.
BLOCK = 8


@njit(cache=True, nogil=True)
def _workspace(m: int, N: int):
    """The arrays _solve_one works in, for m free parameters and N points."""
    return (
        np.empty((15, 2 * N)), np.empty(2 * N), np.empty(N), np.empty(N), np.empty(N),
        np.empty((m, m)), np.empty(m), np.empty((m, m)), np.empty((m, m)), np.empty(m),
        np.empty(4), np.empty(5), np.empty((3, 3)), np.empty(3), np.empty((3, 3)), np.empty(15),
    )


@njit(cache=True, parallel=True, nogil=True)
def solve_batch(
    intr: np.ndarray,  # (K, 4) in/out
    dist: np.ndarray,  # (K, 5) in/out
    R: np.ndarray,  # (K, 3, 3) in/out
    t: np.ndarray,  # (K, 3) in/out
    X: np.ndarray,  # (Kp, N, 3), Kp = 1 or K
    y: np.ndarray,  # (K, N, 2)
    A: np.ndarray,  # (15, m)
    sel: np.ndarray,  # (m,)
    fx_col: int,
    aspect: float,
    max_iterations: int,
    tolerance: float,
    loss: int,
    scale: float,
    cost: np.ndarray,  # (K,) out: unweighted sum of squared residuals
    iterations: np.ndarray,  # (K,) out
) -> None:
    """Solve K independent calibration problems in place, in parallel (blocks of BLOCK problems per workspace)."""
    K = R.shape[0]
    shared = X.shape[0] == 1
    for block in prange((K + BLOCK - 1) // BLOCK):
        J, r, w, sq, sq_t, JtJ, g, H, L, delta, intr_t, dist_t, R_t, t_t, dR, full = _workspace(sel.shape[0], y.shape[1])
        for k in range(block * BLOCK, min(K, (block + 1) * BLOCK)):
            Xk = X[0] if shared else X[k]
            c, it = _solve_one(
                intr[k], dist[k], R[k], t[k], Xk, y[k], A, sel, fx_col, aspect,
                max_iterations, tolerance, loss, scale, 1e-3,
                J, r, w, sq, sq_t, JtJ, g, H, L, delta, intr_t, dist_t, R_t, t_t, dR, full,
            )
            cost[k] = c
            iterations[k] = it


@njit(cache=True, parallel=True, nogil=True)
def monte_carlo_trials(
    intr: np.ndarray,  # (K, 4) in: the reference camera's; out: each trial's estimate
    dist: np.ndarray,  # (K, 5) in/out
    R: np.ndarray,  # (K, 3, 3) in/out
    t: np.ndarray,  # (K, 3) in/out
    X: np.ndarray,  # (K, N, 3) perturbed world points, metres
    y: np.ndarray,  # (K, N, 2) perturbed pixels
    A: np.ndarray,  # (15, m)
    sel: np.ndarray,  # (m,)
    fx_col: int,
    aspect: float,
    max_iterations: int,
    tolerance: float,
    points: np.ndarray,  # (N, 3) the unperturbed points, metres
    uv_points: np.ndarray,  # (N, 2) the reference camera's pixels of points
    ground: np.ndarray,  # (M, 3) ground points in view, metres
    uv_ground: np.ndarray,  # (M, 2) the reference camera's pixels of ground
    uv_probe: np.ndarray,  # (P, 2) pixels whose rays are intersected with the ground plane
    z_plane: float,
    cost: np.ndarray,  # (K,) out: sum of squared residuals (px^2)
    iterations: np.ndarray,  # (K,) out
    proj: np.ndarray,  # (K,) out: RMS pixel difference to the reference over points (px)
    ground_proj: np.ndarray,  # (K,) out: the same over ground (NaN when M = 0)
    hits: np.ndarray,  # (K, P, 3) out: where each estimate's rays of uv_probe meet the ground
) -> None:
    """K Monte-Carlo trials in one parallel pass: each is calibrated (as solve_batch, linear loss) and scored against the reference."""
    K = R.shape[0]
    for block in prange((K + BLOCK - 1) // BLOCK):
        J, r, w, sq, sq_t, JtJ, g, H, L, delta, intr_t, dist_t, R_t, t_t, dR, full = _workspace(sel.shape[0], y.shape[1])
        for k in range(block * BLOCK, min(K, (block + 1) * BLOCK)):
            c, it = _solve_one(
                intr[k], dist[k], R[k], t[k], X[k], y[k], A, sel, fx_col, aspect, max_iterations, tolerance, 0, 1.0, 1e-3,
                J, r, w, sq, sq_t, JtJ, g, H, L, delta, intr_t, dist_t, R_t, t_t, dR, full,
            )
            cost[k] = c
            iterations[k] = it
            proj[k] = _rms_projection_difference(intr[k], dist[k], R[k], t[k], points, uv_points)
            ground_proj[k] = _rms_projection_difference(intr[k], dist[k], R[k], t[k], ground, uv_ground)
            _intersect_into(intr[k], dist[k], R[k], t[k], uv_probe, z_plane, hits[k])


@njit(cache=True, nogil=True)
def normal_equations(
    intr: np.ndarray, dist: np.ndarray, R: np.ndarray, t: np.ndarray,
    X: np.ndarray, y: np.ndarray, w: np.ndarray, sel: np.ndarray, fx_col: int, aspect: float,
    JtJ: np.ndarray, g: np.ndarray, sq: np.ndarray,
) -> None:
    """Normal equations of K problems (K, m, m), (K, m) and squared residuals (K, N); for tests and covariances."""
    shared = X.shape[0] == 1
    for k in range(R.shape[0]):
        _accumulate(intr[k], dist[k], R[k], t[k], X[0] if shared else X[k], y[k], w[k], sel, fx_col, aspect, JtJ[k], g[k], sq[k])


_compile_notice: "Callable[[], None] | None" = None


def announce_compile_with(callback: "Callable[[], None]") -> None:
    """Call ``callback`` once, just before the first solve of this process, if that solve will compile the kernels."""
    global _compile_notice
    _compile_notice = callback


def announce_compile_once() -> None:
    """The hook :func:`announce_compile_with` set, run at most once (a command that fails before its first solve says nothing)."""
    global _compile_notice
    callback, _compile_notice = _compile_notice, None
    if callback is not None and cache_is_cold():
        callback()


def cache_is_cold() -> bool:
    """True when numba's on-disk cache lacks the compiled kernels (first run after install or upgrade).

    The next solve then compiles them: 10-15 s of CPU, 15-45 s of wall time on
    a busy 2-core machine; later runs load them in a fraction of a second.
    Reads numba's cache index only (no compilation), so it is cheap to ask.
    """
    try:
        return not solve_batch._cache._cache_file._load_index()
    except Exception:  # noqa: BLE001 - a numba without this internal: say nothing rather than fail
        return False
