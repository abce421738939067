"""The Monte-Carlo's once-per-call setup, compiled (numba): the reference camera's pixels and every trial's first-step matrix.

Done with numpy these took ~25 small array calls: 0.3 ms per Monte-Carlo
warm, but 1-3 ms when the interpreter's caches are cold (a single
``uncertainty`` run, or a Monte-Carlo right after other work), which at
k = 500 is 2-6 us of every trial. The algebra is that of
``core.camera.project_batch`` (conventions in docs/conventions.md) and of
``core.normal_kernel.jacobian_15``; pure functions on arrays.
"""

from __future__ import annotations

import numpy as np
from numba import njit

from dronecal_field.core.kernels import _cholesky_solve, _intersect_into
from dronecal_field.core.normal_kernel import jacobian_15


@njit(cache=True, nogil=True)
def project(intr: np.ndarray, dist: np.ndarray, R: np.ndarray, t: np.ndarray, X: np.ndarray) -> np.ndarray:
    """Pixels (N, 2) of world points X (N, 3) through one camera (intr (4,), dist (5,), R (3, 3), t (3,))."""
    fx, fy, cx, cy = intr[0], intr[1], intr[2], intr[3]
    k1, k2, p1, p2, k3 = dist[0], dist[1], dist[2], dist[3], dist[4]
    out = np.empty((X.shape[0], 2))
    for n in range(X.shape[0]):
        X0, X1, X2 = X[n, 0], X[n, 1], X[n, 2]
        xc = R[0, 0] * X0 + R[0, 1] * X1 + R[0, 2] * X2 + t[0]
        yc = R[1, 0] * X0 + R[1, 1] * X1 + R[1, 2] * X2 + t[1]
        zc = R[2, 0] * X0 + R[2, 1] * X1 + R[2, 2] * X2 + t[2]
        xn, yn = xc / zc, yc / zc
        r2 = xn * xn + yn * yn
        radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
        xy = xn * yn
        out[n, 0] = fx * (xn * radial + 2.0 * p1 * xy + p2 * (r2 + 2.0 * xn * xn)) + cx
        out[n, 1] = fy * (yn * radial + p1 * (r2 + 2.0 * yn * yn) + 2.0 * p2 * xy) + cy
    return out


@njit(cache=True, nogil=True)
def step_matrix(
    intr: np.ndarray, dist: np.ndarray, R: np.ndarray, t: np.ndarray,
    X: np.ndarray,  # (N, 3) the unperturbed points
    sel: np.ndarray,  # (m,) the parameter each free column moves
    fx_col: int,  # the free column of a tied fx (it also moves fy by aspect), or -1
    aspect: float,
    damping: float,
    Pu: np.ndarray,  # (m, N) out
    Pv: np.ndarray,  # (m, N) out
) -> bool:
    """(J^T J + damping diag(J^T J))^-1 J^T as (Pu, Pv), J (2N, m) the camera's Jacobian at X; False (and zeros) if not positive definite.

    Every trial's first Levenberg-Marquardt step is Pu @ ru + Pv @ rv of its
    residuals at the reference (``core.kernels._reference_step``).
    """
    N = X.shape[0]
    m = sel.shape[0]
    Ju15, Jv15 = np.empty((15, N)), np.empty((15, N))
    jacobian_15(intr, dist, R, t, np.ascontiguousarray(X.T), Ju15, Jv15)
    Ju, Jv = np.empty((m, N)), np.empty((m, N))
    for a in range(m):
        for n in range(N):
            Ju[a, n] = Ju15[sel[a], n]
            Jv[a, n] = Jv15[sel[a], n]
        if a == fx_col:
            for n in range(N):
                Ju[a, n] += aspect * Ju15[1, n]
                Jv[a, n] += aspect * Jv15[1, n]
    H = np.empty((m, m))
    for a in range(m):
        for b in range(a + 1):
            s = 0.0
            for n in range(N):
                s += Ju[a, n] * Ju[b, n] + Jv[a, n] * Jv[b, n]
            H[a, b] = s
            H[b, a] = s
    L, invd, rhs, col, every = np.empty((m, m)), np.empty(m), np.empty(m), np.empty(m), np.arange(m)
    for n in range(N):
        for J, P in ((Ju, Pu), (Jv, Pv)):
            for a in range(m):
                rhs[a] = J[a, n]
            if not _cholesky_solve(H, every, damping, rhs, L, invd, col):
                Pu[:, :] = 0.0
                Pv[:, :] = 0.0
                return False
            for a in range(m):
                P[a, n] = col[a]
    return True


@njit(cache=True, nogil=True)
def ground_grid(
    intr: np.ndarray, dist: np.ndarray, R: np.ndarray, t: np.ndarray, width: int, height: int, ground_z: float,
    nu: int, nv: int, max_range_m: float,
) -> tuple[np.ndarray, np.ndarray]:
    """Pixels (M, 2) of an nu x nv grid over the image (5 %-95 % of each side, rows of v) whose rays meet the plane z = ground_z
    in front of the camera within max_range_m horizontally, and those ground points (M, 3)."""
    uv = np.empty((nu * nv, 2))
    for j in range(nv):
        for i in range(nu):
            # np.linspace(0.05, 0.95, n)'s values: start + k * step, the last one exactly 0.95
            fu = 0.95 if i == nu - 1 else 0.05 + i * ((0.95 - 0.05) / (nu - 1))
            fv = 0.95 if j == nv - 1 else 0.05 + j * ((0.95 - 0.05) / (nv - 1))
            uv[j * nu + i, 0] = fu * (width - 1)
            uv[j * nu + i, 1] = fv * (height - 1)
    g = np.empty((nu * nv, 3))
    _intersect_into(intr, dist, R, t, uv, ground_z, g)
    c0 = -(R[0, 0] * t[0] + R[1, 0] * t[1] + R[2, 0] * t[2])
    c1 = -(R[0, 1] * t[0] + R[1, 1] * t[1] + R[2, 1] * t[2])
    keep = np.zeros(nu * nv, dtype=np.bool_)
    for p in range(nu * nv):
        if np.isfinite(g[p, 0]) and np.isfinite(g[p, 1]) and np.isfinite(g[p, 2]):
            keep[p] = np.sqrt((g[p, 0] - c0) ** 2 + (g[p, 1] - c1) ** 2) < max_range_m
    return uv[keep], g[keep]
