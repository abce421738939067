"""Compiled hot loop of the batched Levenberg-Marquardt (numba), and the Monte-Carlo's per-trial scores.

Each problem (one Monte-Carlo trial, or one calibration) is solved to
convergence inside compiled code, with no Python per iteration. Points and
pixels are held one row per coordinate ((3, N), (2, N)) so every point loop
compiles to vector instructions (``error_model="numpy"``: numba's Python
division check would stop that). A trial step is judged by one pass over the
points that computes only the residuals. Where a step is accepted and the
solve goes on, ``core.normal_kernel`` forms J^T W J and J^T W r of all 15
parameters in one pass without storing the Jacobian; the free parameters are
picked out of them and the step solved by Cholesky. Problems are independent
and run in parallel (``prange``, blocks of BLOCK problems) over numba's
threads. ``monte_carlo_trials`` also applies each trial's noise and scores
the trial against the reference camera in the same pass: projection errors,
the ground rays of ``core.camera.intersect_plane_z``, camera centre and
rotation. The algebra is the same as ``core.camera.project_batch_jacobians``
and ``core.camera.project_batch`` (the tests check they agree); conventions
are in docs/conventions.md.
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

from dronecal_field.core.normal_kernel import normal_equations_15, normal_equations_no_k3  # noqa: E402
from dronecal_field.core.trial_noise import fill_trial_normals, trial_state  # noqa: E402

LOSS_CODES = {"linear": 0, "huber": 1, "cauchy": 2}


@njit(cache=True, fastmath=True, nogil=True, error_model="numpy")
def _weight(sq: float, loss: int, scale: float) -> float:
    if loss == 0:
        return 1.0
    r = np.sqrt(sq) / scale
    if loss == 1:
        return 1.0 if r <= 1.0 else 1.0 / max(r, 1e-12)
    return 1.0 / (1.0 + r * r)


@njit(cache=True, fastmath=True, nogil=True, error_model="numpy")
def _squared_residuals(
    intr: np.ndarray,  # (4,)
    dist: np.ndarray,  # (5,)
    R: np.ndarray,  # (3, 3)
    t: np.ndarray,  # (3,)
    X: np.ndarray,  # (3, N) world x, y, z of every point (one row per coordinate, so the point loop vectorises)
    y: np.ndarray,  # (2, N) observed u, v
    sq: np.ndarray,  # (N,) out
) -> None:
    """Squared reprojection residual of every point: all a trial step needs to be judged."""
    fx, fy, cx, cy = intr[0], intr[1], intr[2], intr[3]
    k1, k2, p1, p2, k3 = dist[0], dist[1], dist[2], dist[3], dist[4]
    r00, r01, r02, r10, r11, r12, r20, r21, r22 = R[0, 0], R[0, 1], R[0, 2], R[1, 0], R[1, 1], R[1, 2], R[2, 0], R[2, 1], R[2, 2]
    t0, t1, t2 = t[0], t[1], t[2]
    Xx, Xy, Xz, yu, yv = X[0], X[1], X[2], y[0], y[1]
    for n in range(yu.shape[0]):
        X0, X1, X2 = Xx[n], Xy[n], Xz[n]
        iz = 1.0 / (r20 * X0 + r21 * X1 + r22 * X2 + t2)
        xn = (r00 * X0 + r01 * X1 + r02 * X2 + t0) * iz
        yn = (r10 * X0 + r11 * X1 + r12 * X2 + t1) * iz
        r2 = xn * xn + yn * yn
        radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
        xy2 = 2.0 * xn * yn
        ru = yu[n] - (fx * (xn * radial + p1 * xy2 + p2 * (r2 + 2.0 * xn * xn)) + cx)
        rv = yv[n] - (fy * (yn * radial + p1 * (r2 + 2.0 * yn * yn) + p2 * xy2) + cy)
        sq[n] = ru * ru + rv * rv


@njit(cache=True, fastmath=True, nogil=True, error_model="numpy")
def _residuals(
    intr: np.ndarray, dist: np.ndarray, R: np.ndarray, t: np.ndarray,
    X: np.ndarray,  # (3, N)
    y: np.ndarray,  # (2, N)
    r: np.ndarray,  # (2, N) out: observed - projected u, v
    sq: np.ndarray,  # (N,) out
) -> float:
    """The reprojection residuals of every point and their sum of squares (``_squared_residuals`` keeping the vectors)."""
    fx, fy, cx, cy = intr[0], intr[1], intr[2], intr[3]
    k1, k2, p1, p2, k3 = dist[0], dist[1], dist[2], dist[3], dist[4]
    r00, r01, r02, r10, r11, r12, r20, r21, r22 = R[0, 0], R[0, 1], R[0, 2], R[1, 0], R[1, 1], R[1, 2], R[2, 0], R[2, 1], R[2, 2]
    t0, t1, t2 = t[0], t[1], t[2]
    Xx, Xy, Xz, yu, yv, ru_out, rv_out = X[0], X[1], X[2], y[0], y[1], r[0], r[1]
    total = 0.0
    for n in range(yu.shape[0]):
        X0, X1, X2 = Xx[n], Xy[n], Xz[n]
        iz = 1.0 / (r20 * X0 + r21 * X1 + r22 * X2 + t2)
        xn = (r00 * X0 + r01 * X1 + r02 * X2 + t0) * iz
        yn = (r10 * X0 + r11 * X1 + r12 * X2 + t1) * iz
        r2 = xn * xn + yn * yn
        radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
        xy2 = 2.0 * xn * yn
        ru = yu[n] - (fx * (xn * radial + p1 * xy2 + p2 * (r2 + 2.0 * xn * xn)) + cx)
        rv = yv[n] - (fy * (yn * radial + p1 * (r2 + 2.0 * yn * yn) + p2 * xy2) + cy)
        ru_out[n] = ru
        rv_out[n] = rv
        sq[n] = ru * ru + rv * rv
        total += sq[n]
    return total


@njit(cache=True, fastmath=True, nogil=True, error_model="numpy")
def _normal_equations(
    intr: np.ndarray, dist: np.ndarray, R: np.ndarray, t: np.ndarray, X: np.ndarray, y: np.ndarray, w: np.ndarray,
    H15: np.ndarray, g15: np.ndarray, sq: np.ndarray, with_k3: bool,
) -> float:
    """``core.normal_kernel``'s normal equations of all 15 parameters, k3's left at 0 unless it is free."""
    if with_k3:
        return normal_equations_15(intr, dist, R, t, X, y, w, H15, g15, sq)
    return normal_equations_no_k3(intr, dist, R, t, X, y, w, H15, g15, sq)


@njit(cache=True, fastmath=True, nogil=True, error_model="numpy")
def _free_normal(H15: np.ndarray, g15: np.ndarray, sel: np.ndarray, fx_col: int, aspect: float, JtJ: np.ndarray, g: np.ndarray) -> None:
    """The normal equations (m, m), (m,) of the free parameters from those of all 15: A^T H15 A and A^T g15.

    Column a of the parameter map is parameter sel[a]; with a tied aspect
    ratio the fx column also moves fy by ``aspect``.
    """
    m = sel.shape[0]
    if fx_col < 0:  # no tied aspect: a plain gather (no branches in the loop: 0.14 -> 0.05 us for m = 14)
        for a in range(m):
            pa = sel[a]
            g[a] = g15[pa]
            for b in range(m):
                JtJ[a, b] = H15[pa, sel[b]]
        return
    for a in range(m):
        pa = sel[a]
        ga = g15[pa]
        if a == fx_col:
            ga += aspect * g15[1]
        g[a] = ga
        for b in range(a, m):
            pb = sel[b]
            v = H15[pa, pb]
            if a == fx_col:
                v += aspect * H15[1, pb]
            if b == fx_col:
                v += aspect * H15[pa, 1]
            if a == fx_col and b == fx_col:
                v += aspect * aspect * H15[1, 1]
            JtJ[a, b] = v
            JtJ[b, a] = v


@njit(cache=True, fastmath=True, nogil=True, error_model="numpy")
def _cholesky_solve(
    JtJ: np.ndarray, idx: np.ndarray, lam: float, b: np.ndarray, L: np.ndarray, invd: np.ndarray, x: np.ndarray,
) -> bool:
    """Solve (H + lam diag(H)) x = c by Cholesky (Marquardt's damping), H = JtJ[idx][:, idx], c = b[idx]; False if not positive definite.

    JtJ (p, p) symmetric, left unchanged (the next damping reuses it); idx
    (m,) picks the rows and columns solved for, so the free parameters' block
    of all 15 is read in place (no gathered copy: 0.1 us per iteration); the
    damped diagonal is formed on the fly. L (m, m) and invd (m,), the
    factor's reciprocal diagonal, are workspace: multiplying by invd keeps
    the divisions (14-20 cycles each, on the critical path) out of the two
    triangular solves. x (m,) out.
    """
    m = idx.shape[0]
    for j in range(m):
        hjj = JtJ[idx[j], idx[j]]
        s = hjj + lam * max(hjj, 1e-12)
        for k in range(j):
            s -= L[j, k] * L[j, k]
        if not (s > 0.0) or not np.isfinite(s):
            return False
        inv = 1.0 / np.sqrt(s)
        invd[j] = inv
        for i in range(j + 1, m):
            s = JtJ[idx[i], idx[j]]
            for k in range(j):
                s -= L[i, k] * L[j, k]
            L[i, j] = s * inv
    for i in range(m):
        s = b[idx[i]]
        for k in range(i):
            s -= L[i, k] * x[k]
        x[i] = s * invd[i]
    for i in range(m - 1, -1, -1):
        s = x[i]
        for k in range(i + 1, m):
            s -= L[k, i] * x[k]
        x[i] = s * invd[i]
    return True


@njit(cache=True, fastmath=True, nogil=True, error_model="numpy")
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


@njit(cache=True, fastmath=True, nogil=True, error_model="numpy")
def _step_camera(
    intr: np.ndarray, dist: np.ndarray, R: np.ndarray, t: np.ndarray, delta: np.ndarray,
    sel: np.ndarray, fx_col: int, aspect: float, full: np.ndarray,
    intr_t: np.ndarray, dist_t: np.ndarray, R_t: np.ndarray, t_t: np.ndarray, dR: np.ndarray,
) -> None:
    """The camera moved by the free-parameter step delta (m,), into intr_t, dist_t, R_t, t_t (rotation on the left)."""
    # full = A @ delta, from the map's structure (column a moves parameter sel[a]; a tied fx also moves fy)
    for i in range(15):
        full[i] = 0.0
    for a in range(sel.shape[0]):
        full[sel[a]] = delta[a]
    if fx_col >= 0:
        full[1] = aspect * delta[fx_col]
    for i in range(4):
        intr_t[i] = intr[i] + full[i]
    for i in range(5):
        dist_t[i] = dist[i] + full[4 + i]
    _rodrigues(full[9], full[10], full[11], dR)
    for i in range(3):
        t_t[i] = t[i] + full[12 + i]
        for j in range(3):
            R_t[i, j] = dR[i, 0] * R[0, j] + dR[i, 1] * R[1, j] + dR[i, 2] * R[2, j]


@njit(cache=True, fastmath=True, nogil=True, error_model="numpy")
def _cost(w: np.ndarray, sq: np.ndarray) -> float:
    c = 0.0
    for n in range(sq.shape[0]):
        c += w[n] * sq[n]
    return c


@njit(cache=True, fastmath=True, nogil=True, error_model="numpy")
def _solve_one(
    intr: np.ndarray, dist: np.ndarray, R: np.ndarray, t: np.ndarray,
    X: np.ndarray, y: np.ndarray, A: np.ndarray, sel: np.ndarray, fx_col: int, aspect: float,
    max_iterations: int, tolerance: float, loss: int, scale: float, damping: float,
    H15: np.ndarray, g15: np.ndarray, w: np.ndarray, sq: np.ndarray, sq_t: np.ndarray,
    JtJ: np.ndarray, g: np.ndarray, invd: np.ndarray, L: np.ndarray, delta: np.ndarray,
    intr_t: np.ndarray, dist_t: np.ndarray, R_t: np.ndarray, t_t: np.ndarray, dR: np.ndarray, full: np.ndarray,
) -> tuple[float, int]:
    """Levenberg-Marquardt for one problem, in place on intr, dist, R, t; returns (cost, iterations).

    X (3, N) world points and y (2, N) pixels, one row per coordinate. The
    arrays after ``damping`` are workspace (H15 (15, 15), g15 (15,), w, sq,
    sq_t (N,), JtJ, L (m, m), g, invd, delta (m,), intr_t (4,), dist_t (5,),
    R_t, dR (3, 3), t_t (3,), full (15,)), reused across problems. A trial
    step is judged on its residuals alone; the normal equations are formed
    only where a step is accepted and the solve goes on.
    """
    N = y.shape[1]
    m = sel.shape[0]
    with_k3 = False
    for a in range(m):
        with_k3 |= sel[a] == 8
    for n in range(N):
        w[n] = 1.0
    cost = _normal_equations(intr, dist, R, t, X, y, w, H15, g15, sq, with_k3)
    if loss != 0:
        for n in range(N):
            w[n] = _weight(sq[n], loss, scale)
        cost = _normal_equations(intr, dist, R, t, X, y, w, H15, g15, sq, with_k3)
    # without a tied aspect the free parameters' block of the 15 normal equations is solved in place; with one,
    # their combination is formed first (_free_normal)
    direct = fx_col < 0
    idx = sel if direct else np.arange(m)
    Hs, gs = (H15, g15) if direct else (JtJ, g)
    if not direct:
        _free_normal(H15, g15, sel, fx_col, aspect, JtJ, g)
    lam = damping
    fails = 0
    it = 0
    for it in range(1, max_iterations + 1):
        cost_t = np.inf
        if _cholesky_solve(Hs, idx, lam, gs, L, invd, delta):
            _step_camera(intr, dist, R, t, delta, sel, fx_col, aspect, full, intr_t, dist_t, R_t, t_t, dR)
            _squared_residuals(intr_t, dist_t, R_t, t_t, X, y, sq_t)
            # judged with the weights the step was computed with, so reweighting cannot fake progress
            cost_t = _cost(w, sq_t)
        if cost_t < cost and np.isfinite(cost_t):
            rel = (cost - cost_t) / max(cost, 1e-300)
            for i in range(4):
                intr[i] = intr_t[i]
            for i in range(5):
                dist[i] = dist_t[i]
            for i in range(3):
                t[i] = t_t[i]
                for j in range(3):
                    R[i, j] = R_t[i, j]
            sq, sq_t = sq_t, sq  # the trial's residuals become the current ones (both are workspace)
            cost = cost_t
            lam = max(lam / 10.0, 1e-9)
            fails = 0
            if rel < tolerance or cost <= 1e-24:
                break
            if loss != 0:
                for n in range(N):
                    w[n] = _weight(sq[n], loss, scale)
            c = _normal_equations(intr, dist, R, t, X, y, w, H15, g15, sq, with_k3)
            if not direct:
                _free_normal(H15, g15, sel, fx_col, aspect, JtJ, g)
            if loss != 0:
                cost = c
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
        sx, sy = (d * ex - b * ey) / det, (a * ey - b * ex) / det
        x, y = x - sx, y - sy
        # Newton converges quadratically: after a step this small the next would change nothing
        if np.abs(sx) + np.abs(sy) < 1e-12:
            break
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


@njit(cache=True, fastmath=True, nogil=True, error_model="numpy")
def _rms_projection_difference(intr: np.ndarray, dist: np.ndarray, R: np.ndarray, t: np.ndarray, X: np.ndarray, uv_ref: np.ndarray) -> float:
    """RMS over points X (3, M) of the pixel distance between this camera's projection and uv_ref (2, M); NaN for M = 0."""
    M = X.shape[1]
    if M == 0:
        return np.nan
    fx, fy, cx, cy = intr[0], intr[1], intr[2], intr[3]
    k1, k2, p1, p2, k3 = dist[0], dist[1], dist[2], dist[3], dist[4]
    r00, r01, r02, r10, r11, r12, r20, r21, r22 = R[0, 0], R[0, 1], R[0, 2], R[1, 0], R[1, 1], R[1, 2], R[2, 0], R[2, 1], R[2, 2]
    t0, t1, t2 = t[0], t[1], t[2]
    Xx, Xy, Xz, uu, vv = X[0], X[1], X[2], uv_ref[0], uv_ref[1]
    s = 0.0
    for n in range(M):
        X0, X1, X2 = Xx[n], Xy[n], Xz[n]
        iz = 1.0 / (r20 * X0 + r21 * X1 + r22 * X2 + t2)
        xn = (r00 * X0 + r01 * X1 + r02 * X2 + t0) * iz
        yn = (r10 * X0 + r11 * X1 + r12 * X2 + t1) * iz
        r2 = xn * xn + yn * yn
        radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
        xy = xn * yn
        du = fx * (xn * radial + 2.0 * p1 * xy + p2 * (r2 + 2.0 * xn * xn)) + cx - uu[n]
        dv = fy * (yn * radial + p1 * (r2 + 2.0 * yn * yn) + 2.0 * p2 * xy) + cy - vv[n]
        s += du * du + dv * dv
    return np.sqrt(s / M)


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
    """The arrays _solve_one works in, for m free parameters and N points (the last two: the points (3, N) and pixels (2, N))."""
    return (
        np.empty((15, 15)), np.empty(15), np.empty(N), np.empty(N), np.empty(N),
        np.empty((m, m)), np.empty(m), np.empty(m), np.empty((m, m)), np.empty(m),
        np.empty(4), np.empty(5), np.empty((3, 3)), np.empty(3), np.empty((3, 3)), np.empty(15),
        np.empty((3, N)), np.empty((2, N)),
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
    N = y.shape[1]
    shared = X.shape[0] == 1
    for block in prange((K + BLOCK - 1) // BLOCK):
        H15, g15, w, sq, sq_t, JtJ, g, invd, L, delta, intr_t, dist_t, R_t, t_t, dR, full, Xs, ys = _workspace(sel.shape[0], N)
        for k in range(block * BLOCK, min(K, (block + 1) * BLOCK)):
            Xk = X[0] if shared else X[k]
            for n in range(N):
                Xs[0, n] = Xk[n, 0]
                Xs[1, n] = Xk[n, 1]
                Xs[2, n] = Xk[n, 2]
                ys[0, n] = y[k, n, 0]
                ys[1, n] = y[k, n, 1]
            c, it = _solve_one(
                intr[k], dist[k], R[k], t[k], Xs, ys, A, sel, fx_col, aspect,
                max_iterations, tolerance, loss, scale, 1e-3,
                H15, g15, w, sq, sq_t, JtJ, g, invd, L, delta, intr_t, dist_t, R_t, t_t, dR, full,
            )
            cost[k] = c
            iterations[k] = it


@njit(cache=True, fastmath=True, nogil=True, error_model="numpy")
def _rotation_vector_between(R: np.ndarray, R0: np.ndarray, out: np.ndarray) -> None:
    """Rotation vector (radians) of R R0^T, both (3, 3) rotations, into out (3,) (scipy's as_rotvec, angle in [0, pi])."""

    def entry(i: int, j: int) -> float:
        return R[i, 0] * R0[j, 0] + R[i, 1] * R0[j, 1] + R[i, 2] * R0[j, 2]

    v0 = 0.5 * (entry(2, 1) - entry(1, 2))
    v1 = 0.5 * (entry(0, 2) - entry(2, 0))
    v2 = 0.5 * (entry(1, 0) - entry(0, 1))
    s = np.sqrt(v0 * v0 + v1 * v1 + v2 * v2)
    c = 0.5 * (entry(0, 0) + entry(1, 1) + entry(2, 2) - 1.0)
    # atan2 keeps small angles exact (arccos of the trace does not); |v| = sin(angle)
    f = np.arctan2(s, c) / s if s > 1e-300 else 1.0
    out[0] = v0 * f
    out[1] = v1 * f
    out[2] = v2 * f


@njit(cache=True, fastmath=True, nogil=True, error_model="numpy")
def _reference_step(
    intr: np.ndarray, dist: np.ndarray, R: np.ndarray, t: np.ndarray, X: np.ndarray, y: np.ndarray,
    Pu: np.ndarray, Pv: np.ndarray, sel: np.ndarray, fx_col: int, aspect: float,
    r: np.ndarray, sq: np.ndarray, delta: np.ndarray, full: np.ndarray,
    intr_t: np.ndarray, dist_t: np.ndarray, R_t: np.ndarray, t_t: np.ndarray, dR: np.ndarray,
) -> tuple[float, float]:
    """A trial's first step from the reference camera, with the reference's Jacobian; (cost before, cost after).

    The trial's points move the Jacobian by ~1e-3 of itself (centimetres at
    metres), so its first Levenberg-Marquardt step (damping 1e-3) is taken
    with the noise-free points' Jacobian J, through the step matrix
    (J^T J + 1e-3 diag(J^T J))^-1 J^T = [Pu Pv] ((m, N) each) computed once
    for all trials: a residual pass and one matrix-vector product instead of
    the normal equations and a factorisation. The step lands in intr_t,
    dist_t, R_t, t_t; the caller keeps it only if the cost fell enough (then
    the solve goes on with exact normal equations), else solves from the
    reference as usual.
    """
    m = sel.shape[0]
    cost = _residuals(intr, dist, R, t, X, y, r, sq)
    ru, rv = r[0], r[1]
    for a in range(m):
        s = 0.0
        pa, pb = Pu[a], Pv[a]
        for n in range(ru.shape[0]):
            s += pa[n] * ru[n] + pb[n] * rv[n]
        delta[a] = s
    _step_camera(intr, dist, R, t, delta, sel, fx_col, aspect, full, intr_t, dist_t, R_t, t_t, dR)
    _squared_residuals(intr_t, dist_t, R_t, t_t, X, y, sq)
    cost_t = 0.0
    for n in range(sq.shape[0]):
        cost_t += sq[n]
    return cost, cost_t


@njit(cache=True, parallel=True, nogil=True)
def monte_carlo_trials(
    intr: np.ndarray,  # (K, 4) in: the reference camera's; out: each trial's estimate
    dist: np.ndarray,  # (K, 5) in/out
    R: np.ndarray,  # (K, 3, 3) in/out
    t: np.ndarray,  # (K, 3) in/out
    key: np.uint64,  # the seed's key (core.trial_noise.seed_key)
    first_trial: int,  # the index of trial 0 of this chunk in the whole Monte-Carlo
    points: np.ndarray,  # (N, 3) the sampled points P, metres
    sigma_3d: np.ndarray,  # (N, 3) metres: trial k's points are P + Z3 * sigma_3d
    pixels: np.ndarray,  # (N, 2) observed pixels p
    sigma_2d: np.ndarray,  # (N,) pixels: trial k's pixels are p + Z2 * sigma_2d
    A: np.ndarray,  # (15, m)
    sel: np.ndarray,  # (m,)
    fx_col: int,
    aspect: float,
    max_iterations: int,
    tolerance: float,
    Pu: np.ndarray,  # (m, N) the first step's matrix for the u residuals (_reference_step; zeros: no such step)
    Pv: np.ndarray,  # (m, N) the same for v
    points_t: np.ndarray,  # (3, N) the unperturbed points, one row per coordinate
    uv_points: np.ndarray,  # (2, N) the reference camera's pixels of points
    ground: np.ndarray,  # (3, M) ground points in view, metres
    uv_ground: np.ndarray,  # (2, M) the reference camera's pixels of ground
    uv_probe: np.ndarray,  # (P, 2) pixels whose rays are intersected with the ground plane
    z_plane: float,
    cost: np.ndarray,  # (K,) out: sum of squared residuals (px^2)
    iterations: np.ndarray,  # (K,) out
    proj: np.ndarray,  # (K,) out: RMS pixel difference to the reference over points (px)
    ground_proj: np.ndarray,  # (K,) out: the same over ground (NaN when M = 0)
    hits: np.ndarray,  # (K, P, 3) out: where each estimate's rays of uv_probe meet the ground
    centre: np.ndarray,  # (K, 3) out: each estimate's camera centre, metres
    rotation: np.ndarray,  # (K, 3) out: rotation vector (radians) of each estimate's R times the reference's R^T
) -> None:
    """K Monte-Carlo trials in one parallel pass: each trial's noise is drawn and applied, it is calibrated (as solve_batch, linear loss) and scored against the reference.

    Trial k's standard normal draws Z3 (N, 3) then Z2 (N, 2) come from its
    own stream, ``core.trial_noise.trial_state(key, first_trial + k)``, in
    that memory order (``trial_noise.fill_trial_normals``;
    ``trial_noise.trial_normals`` replays them); the
    perturbed points are built in the thread's workspace, with no (K, N)
    arrays of draws.
    """
    K = R.shape[0]
    N = points.shape[0]
    for block in prange((K + BLOCK - 1) // BLOCK):
        H15, g15, w, sq, sq_t, JtJ, g, invd, L, delta, intr_t, dist_t, R_t, t_t, dR, full, Xs, ys = _workspace(sel.shape[0], N)
        R0 = np.empty((3, 3))
        r = np.empty((2, N))
        z, redraw = np.empty(5 * N), np.empty(5 * N, np.uint8)
        for k in range(block * BLOCK, min(K, (block + 1) * BLOCK)):
            fill_trial_normals(trial_state(key, first_trial + k), z, redraw)
            for n in range(N):
                for i in range(3):
                    Xs[i, n] = z[3 * n + i] * sigma_3d[n, i] + points[n, i]
            for n in range(N):
                for i in range(2):
                    ys[i, n] = z[3 * N + 2 * n + i] * sigma_2d[n] + pixels[n, i]
            R0[:, :] = R[k]
            c0, c1 = _reference_step(
                intr[k], dist[k], R[k], t[k], Xs, ys, Pu, Pv, sel, fx_col, aspect,
                r, sq, delta, full, intr_t, dist_t, R_t, t_t, dR,
            )
            # the step _solve_one would take first (to ~1e-3 of it), kept when it lowers the cost by more than the
            # tolerance (a smaller drop, as from a zero step, is not trusted to mean converged) and the solve goes on
            if max_iterations >= 2 and np.isfinite(c1) and c0 - c1 > tolerance * c0:
                intr[k, :] = intr_t
                dist[k, :] = dist_t
                R[k, :, :] = R_t
                t[k, :] = t_t
                c, it = _solve_one(
                    intr[k], dist[k], R[k], t[k], Xs, ys, A, sel, fx_col, aspect, max_iterations - 1, tolerance, 0, 1.0, 1e-4,
                    H15, g15, w, sq, sq_t, JtJ, g, invd, L, delta, intr_t, dist_t, R_t, t_t, dR, full,
                )
                it += 1
            else:
                c, it = _solve_one(
                    intr[k], dist[k], R[k], t[k], Xs, ys, A, sel, fx_col, aspect, max_iterations, tolerance, 0, 1.0, 1e-3,
                    H15, g15, w, sq, sq_t, JtJ, g, invd, L, delta, intr_t, dist_t, R_t, t_t, dR, full,
                )
            cost[k] = c
            iterations[k] = it
            proj[k] = _rms_projection_difference(intr[k], dist[k], R[k], t[k], points_t, uv_points)
            ground_proj[k] = _rms_projection_difference(intr[k], dist[k], R[k], t[k], ground, uv_ground)
            _intersect_into(intr[k], dist[k], R[k], t[k], uv_probe, z_plane, hits[k])
            Rk, tk = R[k], t[k]
            for i in range(3):
                centre[k, i] = -(Rk[0, i] * tk[0] + Rk[1, i] * tk[1] + Rk[2, i] * tk[2])
            _rotation_vector_between(Rk, R0, rotation[k])


@njit(cache=True, nogil=True)
def normal_equations(
    intr: np.ndarray, dist: np.ndarray, R: np.ndarray, t: np.ndarray,
    X: np.ndarray, y: np.ndarray, w: np.ndarray, sel: np.ndarray, fx_col: int, aspect: float,
    JtJ: np.ndarray, g: np.ndarray, sq: np.ndarray,
) -> None:
    """Normal equations of K problems (K, m, m), (K, m) and squared residuals (K, N); for tests and covariances.

    X (Kp, N, 3), Kp = 1 or K; y (K, N, 2).
    """
    shared = X.shape[0] == 1
    H15, g15 = np.empty((15, 15)), np.empty(15)
    with_k3 = False
    for a in range(sel.shape[0]):
        with_k3 |= sel[a] == 8
    for k in range(R.shape[0]):
        Xk = np.ascontiguousarray((X[0] if shared else X[k]).T)
        yk = np.ascontiguousarray(y[k].T)
        _normal_equations(intr[k], dist[k], R[k], t[k], Xk, yk, w[k], H15, g15, sq[k], with_k3)
        _free_normal(H15, g15, sel, fx_col, aspect, JtJ[k], g[k])


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
