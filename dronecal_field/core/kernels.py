"""Compiled hot loop of the batched Levenberg-Marquardt (numba).

One pass over every (problem, point) pair projects the point, forms its two
Jacobian rows for the free parameters and accumulates the normal equations
J^T W J, J^T W r directly, so no (K, 2N, m) Jacobian is ever stored. The
algebra is the same as ``core.camera.project_batch_jacobians`` (the tests
check the two agree); conventions are in docs/conventions.md.
"""

from __future__ import annotations

import numpy as np
from numba import njit


@njit(cache=True, fastmath=True, nogil=True)
def normal_equations(
    intr: np.ndarray,  # (K, 4)
    dist: np.ndarray,  # (K, 5)
    R: np.ndarray,  # (K, 3, 3)
    t: np.ndarray,  # (K, 3)
    X: np.ndarray,  # (Kp, N, 3), Kp = 1 or K
    y: np.ndarray,  # (K, N, 2)
    w: np.ndarray,  # (K, N) per-point weights
    sel: np.ndarray,  # (m,) index into the 15 full parameters of each free column
    fx_col: int,  # free column of fx when fy is tied to it, else -1
    aspect: float,  # fy / fx when tied
    JtJ: np.ndarray,  # (K, m, m) out
    g: np.ndarray,  # (K, m) out
    sq: np.ndarray,  # (K, N) out: squared residual norm per point
) -> None:
    K = R.shape[0]
    N = y.shape[1]
    m = sel.shape[0]
    shared = X.shape[0] == 1
    jf_u = np.empty(15)
    jf_v = np.empty(15)
    ju = np.empty(m)
    jv = np.empty(m)
    for k in range(K):
        fx, fy, cx, cy = intr[k, 0], intr[k, 1], intr[k, 2], intr[k, 3]
        k1, k2, p1, p2, k3 = dist[k, 0], dist[k, 1], dist[k, 2], dist[k, 3], dist[k, 4]
        for a in range(m):
            g[k, a] = 0.0
            for b in range(m):
                JtJ[k, a, b] = 0.0
        kp = 0 if shared else k
        for n in range(N):
            X0, X1, X2 = X[kp, n, 0], X[kp, n, 1], X[kp, n, 2]
            ax = R[k, 0, 0] * X0 + R[k, 0, 1] * X1 + R[k, 0, 2] * X2
            ay = R[k, 1, 0] * X0 + R[k, 1, 1] * X1 + R[k, 1, 2] * X2
            az = R[k, 2, 0] * X0 + R[k, 2, 1] * X1 + R[k, 2, 2] * X2
            iz = 1.0 / (az + t[k, 2])
            xn = (ax + t[k, 0]) * iz
            yn = (ay + t[k, 1]) * iz
            r2 = xn * xn + yn * yn
            r4 = r2 * r2
            radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
            xy2 = 2.0 * xn * yn
            xd = xn * radial + p1 * xy2 + p2 * (r2 + 2.0 * xn * xn)
            yd = yn * radial + p1 * (r2 + 2.0 * yn * yn) + p2 * xy2
            ru = y[k, n, 0] - (fx * xd + cx)
            rv = y[k, n, 1] - (fy * yd + cy)
            sq[k, n] = ru * ru + rv * rv
            wn = w[k, n]
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
                g[k, a] += wu * ru + wv * rv
                for b in range(a, m):
                    JtJ[k, a, b] += wu * ju[b] + wv * jv[b]
        for a in range(m):
            for b in range(a + 1, m):
                JtJ[k, b, a] = JtJ[k, a, b]
