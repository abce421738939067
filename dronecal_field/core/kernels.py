"""Compiled hot loop of the batched Levenberg-Marquardt (numba).

Each problem (one Monte-Carlo trial, or one calibration) is solved to
convergence inside compiled code: one pass over its points projects them,
forms the two Jacobian rows of each for the free parameters and accumulates
the normal equations J^T W J, J^T W r directly, so no Jacobian is stored and
no Python runs per iteration. Problems are independent and run in parallel
(``prange``) over numba's threads. The algebra is the same as
``core.camera.project_batch_jacobians`` (the tests check the two agree);
conventions are in docs/conventions.md.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
from numba import njit, prange

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
    """Normal equations of one problem at one parameter value."""
    N = y.shape[0]
    m = sel.shape[0]
    fx, fy, cx, cy = intr[0], intr[1], intr[2], intr[3]
    k1, k2, p1, p2, k3 = dist[0], dist[1], dist[2], dist[3], dist[4]
    jf_u = np.empty(15)
    jf_v = np.empty(15)
    ju = np.empty(m)
    jv = np.empty(m)
    for a in range(m):
        g[a] = 0.0
        for b in range(m):
            JtJ[a, b] = 0.0
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
        wn = w[n]
        if wn == 0.0:
            continue
        drad = k1 + r2 * (2.0 * k2 + 3.0 * k3 * r2)
        dxd_dy = xy2 * drad + 2.0 * p1 * xn + 2.0 * p2 * yn
        a00 = fx * (radial + 2.0 * xn * xn * drad + 2.0 * p1 * yn + 6.0 * p2 * xn) * iz
        a01 = fx * dxd_dy * iz
        a10 = fy * dxd_dy * iz
        a11 = fy * (radial + 2.0 * yn * yn * drad + 6.0 * p1 * yn + 2.0 * p2 * xn) * iz
        gu2 = -(a00 * xn + a01 * yn)
        gv2 = -(a10 * xn + a11 * yn)
        jf_u[0] = xd
        jf_u[1] = 0.0
        jf_u[2] = 1.0
        jf_u[3] = 0.0
        jf_u[4] = fx * xn * r2
        jf_u[5] = fx * xn * r4
        jf_u[6] = fx * xy2
        jf_u[7] = fx * (r2 + 2.0 * xn * xn)
        jf_u[8] = fx * xn * r4 * r2
        jf_u[9] = ay * gu2 - az * a01
        jf_u[10] = az * a00 - ax * gu2
        jf_u[11] = ax * a01 - ay * a00
        jf_u[12] = a00
        jf_u[13] = a01
        jf_u[14] = gu2
        jf_v[0] = 0.0
        jf_v[1] = yd
        jf_v[2] = 0.0
        jf_v[3] = 1.0
        jf_v[4] = fy * yn * r2
        jf_v[5] = fy * yn * r4
        jf_v[6] = fy * (r2 + 2.0 * yn * yn)
        jf_v[7] = fy * xy2
        jf_v[8] = fy * yn * r4 * r2
        jf_v[9] = ay * gv2 - az * a11
        jf_v[10] = az * a10 - ax * gv2
        jf_v[11] = ax * a11 - ay * a10
        jf_v[12] = a10
        jf_v[13] = a11
        jf_v[14] = gv2
        for a in range(m):
            ju[a] = jf_u[sel[a]]
            jv[a] = jf_v[sel[a]]
        if fx_col >= 0:
            ju[fx_col] += aspect * jf_u[1]
            jv[fx_col] += aspect * jf_v[1]
        for a in range(m):
            wu = wn * ju[a]
            wv = wn * jv[a]
            g[a] += wu * ru + wv * rv
            for b in range(a, m):
                JtJ[a, b] += wu * ju[b] + wv * jv[b]
    for a in range(m):
        for b in range(a + 1, m):
            JtJ[b, a] = JtJ[a, b]


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
    max_iterations: int, tolerance: float, loss: int, scale: float,
) -> tuple[float, int]:
    """Levenberg-Marquardt for one problem, in place on intr, dist, R, t; returns (cost, iterations)."""
    N = y.shape[0]
    m = sel.shape[0]
    JtJ = np.empty((m, m))
    g = np.empty(m)
    sq = np.empty(N)
    JtJ_t = np.empty((m, m))
    g_t = np.empty(m)
    sq_t = np.empty(N)
    H = np.empty((m, m))
    w = np.ones(N)
    intr_t = np.empty(4)
    dist_t = np.empty(5)
    R_t = np.empty((3, 3))
    t_t = np.empty(3)
    dR = np.empty((3, 3))
    full = np.empty(15)
    _accumulate(intr, dist, R, t, X, y, w, sel, fx_col, aspect, JtJ, g, sq)
    if loss != 0:
        for n in range(N):
            w[n] = _weight(sq[n], loss, scale)
        _accumulate(intr, dist, R, t, X, y, w, sel, fx_col, aspect, JtJ, g, sq)
    cost = _cost(w, sq)
    lam = 1e-3
    fails = 0
    it = 0
    for it in range(1, max_iterations + 1):
        for a in range(m):
            for b in range(m):
                H[a, b] = JtJ[a, b]
            H[a, a] += lam * max(JtJ[a, a], 1e-12)
        delta = np.linalg.solve(H, g)
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
        _accumulate(intr_t, dist_t, R_t, t_t, X, y, w, sel, fx_col, aspect, JtJ_t, g_t, sq_t)
        # judged with the weights the step was computed with, so reweighting cannot fake progress
        cost_t = _cost(w, sq_t)
        if cost_t < cost and np.isfinite(cost_t):
            rel = (cost - cost_t) / max(cost, 1e-300)
            intr[:] = intr_t
            dist[:] = dist_t
            R[:, :] = R_t
            t[:] = t_t
            JtJ[:, :] = JtJ_t
            g[:] = g_t
            sq[:] = sq_t
            cost = cost_t
            if loss != 0:
                for n in range(N):
                    w[n] = _weight(sq[n], loss, scale)
                _accumulate(intr, dist, R, t, X, y, w, sel, fx_col, aspect, JtJ, g, sq)
                cost = _cost(w, sq)
            lam = max(lam / 10.0, 1e-9)
            fails = 0
            if rel < tolerance or cost <= 1e-24:
                break
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
    """Solve K independent calibration problems in place, in parallel."""
    K = R.shape[0]
    shared = X.shape[0] == 1
    for k in prange(K):
        Xk = X[0] if shared else X[k]
        c, it = _solve_one(intr[k], dist[k], R[k], t[k], Xk, y[k], A, sel, fx_col, aspect, max_iterations, tolerance, loss, scale)
        cost[k] = c
        iterations[k] = it


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
