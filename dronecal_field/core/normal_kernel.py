"""The normal equations of one calibration problem in one vectorised pass over its points (numba).

J^T W J over all 15 camera parameters and J^T W r, accumulated point by
point with one scalar accumulator per entry: no Jacobian is stored, so the
point loop has no stores but the squared residuals and compiles to vector
instructions (8 points at a time on AVX-512), where forming the Jacobian rows
and then their dot products cost about 4x as much on the paper's grid. The
entries that are zero for every point (fx against fy or cy, cx against fy
or cy) are left out. The algebra is that of
``core.camera.project_batch_jacobians`` (rotation perturbation on the left,
conventions in docs/conventions.md); ``core.kernels`` picks the free
parameters out of the result. The accumulator lines are written out in full
(numba compiles no loop over a variable number of scalars).
``normal_equations_no_k3`` is the same without k3's row and column, for
every model but 'full' (the Monte-Carlo's default fixes k3, as OpenCV's
CALIB_FIX_K3 does).
"""

from __future__ import annotations

import numpy as np
from numba import njit


@njit(cache=True, fastmath=True, nogil=True, error_model="numpy")
def normal_equations_15(
    intr: np.ndarray,  # (4,)
    dist: np.ndarray,  # (5,)
    R: np.ndarray,  # (3, 3)
    t: np.ndarray,  # (3,)
    X: np.ndarray,  # (3, N) world x, y, z of every point, one row per coordinate
    y: np.ndarray,  # (2, N) observed u, v
    w: np.ndarray,  # (N,) weights
    H: np.ndarray,  # (15, 15) out: J^T W J
    g: np.ndarray,  # (15,) out: J^T W r, r = observed - projected
    sq: np.ndarray,  # (N,) out: unweighted squared residuals
) -> float:
    """Normal equations of all 15 parameters at this camera; returns the weighted cost sum(w * sq)."""
    fx, fy, cx, cy = intr[0], intr[1], intr[2], intr[3]
    k1, k2, p1, p2, k3 = dist[0], dist[1], dist[2], dist[3], dist[4]
    r00, r01, r02, r10, r11, r12, r20, r21, r22 = R[0, 0], R[0, 1], R[0, 2], R[1, 0], R[1, 1], R[1, 2], R[2, 0], R[2, 1], R[2, 2]
    t0, t1, t2 = t[0], t[1], t[2]
    Xx, Xy, Xz, yu, yv = X[0], X[1], X[2], y[0], y[1]
    cost = 0.0
    g0 = h0_0 = h0_2 = h0_4 = h0_5 = h0_6 = h0_7 = h0_8 = h0_9 = h0_10 = h0_11 = h0_12 = 0.0
    h0_13 = h0_14 = g1 = h1_1 = h1_3 = h1_4 = h1_5 = h1_6 = h1_7 = h1_8 = h1_9 = h1_10 = 0.0
    h1_11 = h1_12 = h1_13 = h1_14 = g2 = h2_2 = h2_4 = h2_5 = h2_6 = h2_7 = h2_8 = h2_9 = 0.0
    h2_10 = h2_11 = h2_12 = h2_13 = h2_14 = g3 = h3_3 = h3_4 = h3_5 = h3_6 = h3_7 = h3_8 = 0.0
    h3_9 = h3_10 = h3_11 = h3_12 = h3_13 = h3_14 = g4 = h4_4 = h4_5 = h4_6 = h4_7 = h4_8 = 0.0
    h4_9 = h4_10 = h4_11 = h4_12 = h4_13 = h4_14 = g5 = h5_5 = h5_6 = h5_7 = h5_8 = h5_9 = 0.0
    h5_10 = h5_11 = h5_12 = h5_13 = h5_14 = g6 = h6_6 = h6_7 = h6_8 = h6_9 = h6_10 = h6_11 = 0.0
    h6_12 = h6_13 = h6_14 = g7 = h7_7 = h7_8 = h7_9 = h7_10 = h7_11 = h7_12 = h7_13 = h7_14 = 0.0
    g8 = h8_8 = h8_9 = h8_10 = h8_11 = h8_12 = h8_13 = h8_14 = g9 = h9_9 = h9_10 = h9_11 = 0.0
    h9_12 = h9_13 = h9_14 = g10 = h10_10 = h10_11 = h10_12 = h10_13 = h10_14 = g11 = h11_11 = h11_12 = 0.0
    h11_13 = h11_14 = g12 = h12_12 = h12_13 = h12_14 = g13 = h13_13 = h13_14 = g14 = h14_14 = 0.0
    for n in range(yu.shape[0]):
        X0, X1, X2 = Xx[n], Xy[n], Xz[n]
        ax = r00 * X0 + r01 * X1 + r02 * X2
        ay = r10 * X0 + r11 * X1 + r12 * X2
        az = r20 * X0 + r21 * X1 + r22 * X2
        iz = 1.0 / (az + t2)
        xn = (ax + t0) * iz
        yn = (ay + t1) * iz
        r2 = xn * xn + yn * yn
        r4 = r2 * r2
        r6 = r4 * r2
        radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
        xy2 = 2.0 * xn * yn
        xd = xn * radial + p1 * xy2 + p2 * (r2 + 2.0 * xn * xn)
        yd = yn * radial + p1 * (r2 + 2.0 * yn * yn) + p2 * xy2
        ru = yu[n] - (fx * xd + cx)
        rv = yv[n] - (fy * yd + cy)
        s = ru * ru + rv * rv
        sq[n] = s
        wn = w[n]
        cost += wn * s
        sw = np.sqrt(wn)
        ruw = sw * ru
        rvw = sw * rv
        drad = k1 + r2 * (2.0 * k2 + 3.0 * k3 * r2)
        dxd_dy = xy2 * drad + 2.0 * p1 * xn + 2.0 * p2 * yn
        a00 = fx * (radial + 2.0 * xn * xn * drad + 2.0 * p1 * yn + 6.0 * p2 * xn) * iz
        a01 = fx * dxd_dy * iz
        a10 = fy * dxd_dy * iz
        a11 = fy * (radial + 2.0 * yn * yn * drad + 6.0 * p1 * yn + 2.0 * p2 * xn) * iz
        gu2 = -(a00 * xn + a01 * yn)
        gv2 = -(a10 * xn + a11 * yn)
        u0 = sw * xd
        v1 = sw * yd
        u2 = sw
        v3 = sw
        u4 = sw * fx * xn * r2
        v4 = sw * fy * yn * r2
        u5 = sw * fx * xn * r4
        v5 = sw * fy * yn * r4
        u6 = sw * fx * xy2
        v6 = sw * fy * (r2 + 2.0 * yn * yn)
        u7 = sw * fx * (r2 + 2.0 * xn * xn)
        v7 = sw * fy * xy2
        u8 = sw * fx * xn * r6
        v8 = sw * fy * yn * r6
        u9 = sw * (ay * gu2 - az * a01)
        v9 = sw * (ay * gv2 - az * a11)
        u10 = sw * (az * a00 - ax * gu2)
        v10 = sw * (az * a10 - ax * gv2)
        u11 = sw * (ax * a01 - ay * a00)
        v11 = sw * (ax * a11 - ay * a10)
        u12 = sw * a00
        v12 = sw * a10
        u13 = sw * a01
        v13 = sw * a11
        u14 = sw * gu2
        v14 = sw * gv2
        g0 += u0 * ruw
        h0_0 += u0 * u0
        h0_2 += u0 * u2
        h0_4 += u0 * u4
        h0_5 += u0 * u5
        h0_6 += u0 * u6
        h0_7 += u0 * u7
        h0_8 += u0 * u8
        h0_9 += u0 * u9
        h0_10 += u0 * u10
        h0_11 += u0 * u11
        h0_12 += u0 * u12
        h0_13 += u0 * u13
        h0_14 += u0 * u14
        g1 += v1 * rvw
        h1_1 += v1 * v1
        h1_3 += v1 * v3
        h1_4 += v1 * v4
        h1_5 += v1 * v5
        h1_6 += v1 * v6
        h1_7 += v1 * v7
        h1_8 += v1 * v8
        h1_9 += v1 * v9
        h1_10 += v1 * v10
        h1_11 += v1 * v11
        h1_12 += v1 * v12
        h1_13 += v1 * v13
        h1_14 += v1 * v14
        g2 += u2 * ruw
        h2_2 += u2 * u2
        h2_4 += u2 * u4
        h2_5 += u2 * u5
        h2_6 += u2 * u6
        h2_7 += u2 * u7
        h2_8 += u2 * u8
        h2_9 += u2 * u9
        h2_10 += u2 * u10
        h2_11 += u2 * u11
        h2_12 += u2 * u12
        h2_13 += u2 * u13
        h2_14 += u2 * u14
        g3 += v3 * rvw
        h3_3 += v3 * v3
        h3_4 += v3 * v4
        h3_5 += v3 * v5
        h3_6 += v3 * v6
        h3_7 += v3 * v7
        h3_8 += v3 * v8
        h3_9 += v3 * v9
        h3_10 += v3 * v10
        h3_11 += v3 * v11
        h3_12 += v3 * v12
        h3_13 += v3 * v13
        h3_14 += v3 * v14
        g4 += u4 * ruw + v4 * rvw
        h4_4 += u4 * u4 + v4 * v4
        h4_5 += u4 * u5 + v4 * v5
        h4_6 += u4 * u6 + v4 * v6
        h4_7 += u4 * u7 + v4 * v7
        h4_8 += u4 * u8 + v4 * v8
        h4_9 += u4 * u9 + v4 * v9
        h4_10 += u4 * u10 + v4 * v10
        h4_11 += u4 * u11 + v4 * v11
        h4_12 += u4 * u12 + v4 * v12
        h4_13 += u4 * u13 + v4 * v13
        h4_14 += u4 * u14 + v4 * v14
        g5 += u5 * ruw + v5 * rvw
        h5_5 += u5 * u5 + v5 * v5
        h5_6 += u5 * u6 + v5 * v6
        h5_7 += u5 * u7 + v5 * v7
        h5_8 += u5 * u8 + v5 * v8
        h5_9 += u5 * u9 + v5 * v9
        h5_10 += u5 * u10 + v5 * v10
        h5_11 += u5 * u11 + v5 * v11
        h5_12 += u5 * u12 + v5 * v12
        h5_13 += u5 * u13 + v5 * v13
        h5_14 += u5 * u14 + v5 * v14
        g6 += u6 * ruw + v6 * rvw
        h6_6 += u6 * u6 + v6 * v6
        h6_7 += u6 * u7 + v6 * v7
        h6_8 += u6 * u8 + v6 * v8
        h6_9 += u6 * u9 + v6 * v9
        h6_10 += u6 * u10 + v6 * v10
        h6_11 += u6 * u11 + v6 * v11
        h6_12 += u6 * u12 + v6 * v12
        h6_13 += u6 * u13 + v6 * v13
        h6_14 += u6 * u14 + v6 * v14
        g7 += u7 * ruw + v7 * rvw
        h7_7 += u7 * u7 + v7 * v7
        h7_8 += u7 * u8 + v7 * v8
        h7_9 += u7 * u9 + v7 * v9
        h7_10 += u7 * u10 + v7 * v10
        h7_11 += u7 * u11 + v7 * v11
        h7_12 += u7 * u12 + v7 * v12
        h7_13 += u7 * u13 + v7 * v13
        h7_14 += u7 * u14 + v7 * v14
        g8 += u8 * ruw + v8 * rvw
        h8_8 += u8 * u8 + v8 * v8
        h8_9 += u8 * u9 + v8 * v9
        h8_10 += u8 * u10 + v8 * v10
        h8_11 += u8 * u11 + v8 * v11
        h8_12 += u8 * u12 + v8 * v12
        h8_13 += u8 * u13 + v8 * v13
        h8_14 += u8 * u14 + v8 * v14
        g9 += u9 * ruw + v9 * rvw
        h9_9 += u9 * u9 + v9 * v9
        h9_10 += u9 * u10 + v9 * v10
        h9_11 += u9 * u11 + v9 * v11
        h9_12 += u9 * u12 + v9 * v12
        h9_13 += u9 * u13 + v9 * v13
        h9_14 += u9 * u14 + v9 * v14
        g10 += u10 * ruw + v10 * rvw
        h10_10 += u10 * u10 + v10 * v10
        h10_11 += u10 * u11 + v10 * v11
        h10_12 += u10 * u12 + v10 * v12
        h10_13 += u10 * u13 + v10 * v13
        h10_14 += u10 * u14 + v10 * v14
        g11 += u11 * ruw + v11 * rvw
        h11_11 += u11 * u11 + v11 * v11
        h11_12 += u11 * u12 + v11 * v12
        h11_13 += u11 * u13 + v11 * v13
        h11_14 += u11 * u14 + v11 * v14
        g12 += u12 * ruw + v12 * rvw
        h12_12 += u12 * u12 + v12 * v12
        h12_13 += u12 * u13 + v12 * v13
        h12_14 += u12 * u14 + v12 * v14
        g13 += u13 * ruw + v13 * rvw
        h13_13 += u13 * u13 + v13 * v13
        h13_14 += u13 * u14 + v13 * v14
        g14 += u14 * ruw + v14 * rvw
        h14_14 += u14 * u14 + v14 * v14
    g[0] = g0
    H[0, 0], H[0, 1], H[0, 2], H[0, 3], H[0, 4], H[0, 5] = h0_0, 0.0, h0_2, 0.0, h0_4, h0_5
    H[0, 6], H[0, 7], H[0, 8], H[0, 9], H[0, 10], H[0, 11] = h0_6, h0_7, h0_8, h0_9, h0_10, h0_11
    H[0, 12], H[0, 13], H[0, 14] = h0_12, h0_13, h0_14
    g[1] = g1
    H[1, 1], H[1, 2], H[1, 3], H[1, 4], H[1, 5], H[1, 6] = h1_1, 0.0, h1_3, h1_4, h1_5, h1_6
    H[1, 7], H[1, 8], H[1, 9], H[1, 10], H[1, 11], H[1, 12] = h1_7, h1_8, h1_9, h1_10, h1_11, h1_12
    H[1, 13], H[1, 14] = h1_13, h1_14
    g[2] = g2
    H[2, 2], H[2, 3], H[2, 4], H[2, 5], H[2, 6], H[2, 7] = h2_2, 0.0, h2_4, h2_5, h2_6, h2_7
    H[2, 8], H[2, 9], H[2, 10], H[2, 11], H[2, 12], H[2, 13] = h2_8, h2_9, h2_10, h2_11, h2_12, h2_13
    H[2, 14] = h2_14
    g[3] = g3
    H[3, 3], H[3, 4], H[3, 5], H[3, 6], H[3, 7], H[3, 8] = h3_3, h3_4, h3_5, h3_6, h3_7, h3_8
    H[3, 9], H[3, 10], H[3, 11], H[3, 12], H[3, 13], H[3, 14] = h3_9, h3_10, h3_11, h3_12, h3_13, h3_14
    g[4] = g4
    H[4, 4], H[4, 5], H[4, 6], H[4, 7], H[4, 8], H[4, 9] = h4_4, h4_5, h4_6, h4_7, h4_8, h4_9
    H[4, 10], H[4, 11], H[4, 12], H[4, 13], H[4, 14] = h4_10, h4_11, h4_12, h4_13, h4_14
    g[5] = g5
    H[5, 5], H[5, 6], H[5, 7], H[5, 8], H[5, 9], H[5, 10] = h5_5, h5_6, h5_7, h5_8, h5_9, h5_10
    H[5, 11], H[5, 12], H[5, 13], H[5, 14] = h5_11, h5_12, h5_13, h5_14
    g[6] = g6
    H[6, 6], H[6, 7], H[6, 8], H[6, 9], H[6, 10], H[6, 11] = h6_6, h6_7, h6_8, h6_9, h6_10, h6_11
    H[6, 12], H[6, 13], H[6, 14] = h6_12, h6_13, h6_14
    g[7] = g7
    H[7, 7], H[7, 8], H[7, 9], H[7, 10], H[7, 11], H[7, 12] = h7_7, h7_8, h7_9, h7_10, h7_11, h7_12
    H[7, 13], H[7, 14] = h7_13, h7_14
    g[8] = g8
    H[8, 8], H[8, 9], H[8, 10], H[8, 11], H[8, 12], H[8, 13] = h8_8, h8_9, h8_10, h8_11, h8_12, h8_13
    H[8, 14] = h8_14
    g[9] = g9
    H[9, 9], H[9, 10], H[9, 11], H[9, 12], H[9, 13], H[9, 14] = h9_9, h9_10, h9_11, h9_12, h9_13, h9_14
    g[10] = g10
    H[10, 10], H[10, 11], H[10, 12], H[10, 13], H[10, 14] = h10_10, h10_11, h10_12, h10_13, h10_14
    g[11] = g11
    H[11, 11], H[11, 12], H[11, 13], H[11, 14] = h11_11, h11_12, h11_13, h11_14
    g[12] = g12
    H[12, 12], H[12, 13], H[12, 14] = h12_12, h12_13, h12_14
    g[13] = g13
    H[13, 13], H[13, 14] = h13_13, h13_14
    g[14] = g14
    H[14, 14] = h14_14
    for a in range(15):  # the lower triangle mirrors the upper
        for b in range(a):
            H[a, b] = H[b, a]
    return cost


@njit(cache=True, fastmath=True, nogil=True, error_model="numpy")
def normal_equations_no_k3(
    intr: np.ndarray,  # (4,)
    dist: np.ndarray,  # (5,)
    R: np.ndarray,  # (3, 3)
    t: np.ndarray,  # (3,)
    X: np.ndarray,  # (3, N) world x, y, z of every point, one row per coordinate
    y: np.ndarray,  # (2, N) observed u, v
    w: np.ndarray,  # (N,) weights
    H: np.ndarray,  # (15, 15) out: J^T W J
    g: np.ndarray,  # (15,) out: J^T W r, r = observed - projected
    sq: np.ndarray,  # (N,) out: unweighted squared residuals
) -> float:
    """:func:`normal_equations_15` for a model with k3 fixed (all but 'full'): k3's row and column are left at 0 (about 12 % less work)."""
    fx, fy, cx, cy = intr[0], intr[1], intr[2], intr[3]
    k1, k2, p1, p2, k3 = dist[0], dist[1], dist[2], dist[3], dist[4]
    r00, r01, r02, r10, r11, r12, r20, r21, r22 = R[0, 0], R[0, 1], R[0, 2], R[1, 0], R[1, 1], R[1, 2], R[2, 0], R[2, 1], R[2, 2]
    t0, t1, t2 = t[0], t[1], t[2]
    Xx, Xy, Xz, yu, yv = X[0], X[1], X[2], y[0], y[1]
    cost = 0.0
    g0 = h0_0 = h0_2 = h0_4 = h0_5 = h0_6 = h0_7 = h0_9 = h0_10 = h0_11 = h0_12 = 0.0
    h0_13 = h0_14 = g1 = h1_1 = h1_3 = h1_4 = h1_5 = h1_6 = h1_7 = h1_9 = h1_10 = 0.0
    h1_11 = h1_12 = h1_13 = h1_14 = g2 = h2_2 = h2_4 = h2_5 = h2_6 = h2_7 = h2_9 = 0.0
    h2_10 = h2_11 = h2_12 = h2_13 = h2_14 = g3 = h3_3 = h3_4 = h3_5 = h3_6 = h3_7 = 0.0
    h3_9 = h3_10 = h3_11 = h3_12 = h3_13 = h3_14 = g4 = h4_4 = h4_5 = h4_6 = h4_7 = 0.0
    h4_9 = h4_10 = h4_11 = h4_12 = h4_13 = h4_14 = g5 = h5_5 = h5_6 = h5_7 = h5_9 = 0.0
    h5_10 = h5_11 = h5_12 = h5_13 = h5_14 = g6 = h6_6 = h6_7 = h6_9 = h6_10 = h6_11 = 0.0
    h6_12 = h6_13 = h6_14 = g7 = h7_7 = h7_9 = h7_10 = h7_11 = h7_12 = h7_13 = h7_14 = 0.0
    g9 = h9_9 = h9_10 = h9_11 = 0.0
    h9_12 = h9_13 = h9_14 = g10 = h10_10 = h10_11 = h10_12 = h10_13 = h10_14 = g11 = h11_11 = h11_12 = 0.0
    h11_13 = h11_14 = g12 = h12_12 = h12_13 = h12_14 = g13 = h13_13 = h13_14 = g14 = h14_14 = 0.0
    for n in range(yu.shape[0]):
        X0, X1, X2 = Xx[n], Xy[n], Xz[n]
        ax = r00 * X0 + r01 * X1 + r02 * X2
        ay = r10 * X0 + r11 * X1 + r12 * X2
        az = r20 * X0 + r21 * X1 + r22 * X2
        iz = 1.0 / (az + t2)
        xn = (ax + t0) * iz
        yn = (ay + t1) * iz
        r2 = xn * xn + yn * yn
        r4 = r2 * r2
        radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
        xy2 = 2.0 * xn * yn
        xd = xn * radial + p1 * xy2 + p2 * (r2 + 2.0 * xn * xn)
        yd = yn * radial + p1 * (r2 + 2.0 * yn * yn) + p2 * xy2
        ru = yu[n] - (fx * xd + cx)
        rv = yv[n] - (fy * yd + cy)
        s = ru * ru + rv * rv
        sq[n] = s
        wn = w[n]
        cost += wn * s
        sw = np.sqrt(wn)
        ruw = sw * ru
        rvw = sw * rv
        drad = k1 + r2 * (2.0 * k2 + 3.0 * k3 * r2)
        dxd_dy = xy2 * drad + 2.0 * p1 * xn + 2.0 * p2 * yn
        a00 = fx * (radial + 2.0 * xn * xn * drad + 2.0 * p1 * yn + 6.0 * p2 * xn) * iz
        a01 = fx * dxd_dy * iz
        a10 = fy * dxd_dy * iz
        a11 = fy * (radial + 2.0 * yn * yn * drad + 6.0 * p1 * yn + 2.0 * p2 * xn) * iz
        gu2 = -(a00 * xn + a01 * yn)
        gv2 = -(a10 * xn + a11 * yn)
        u0 = sw * xd
        v1 = sw * yd
        u2 = sw
        v3 = sw
        u4 = sw * fx * xn * r2
        v4 = sw * fy * yn * r2
        u5 = sw * fx * xn * r4
        v5 = sw * fy * yn * r4
        u6 = sw * fx * xy2
        v6 = sw * fy * (r2 + 2.0 * yn * yn)
        u7 = sw * fx * (r2 + 2.0 * xn * xn)
        v7 = sw * fy * xy2
        u9 = sw * (ay * gu2 - az * a01)
        v9 = sw * (ay * gv2 - az * a11)
        u10 = sw * (az * a00 - ax * gu2)
        v10 = sw * (az * a10 - ax * gv2)
        u11 = sw * (ax * a01 - ay * a00)
        v11 = sw * (ax * a11 - ay * a10)
        u12 = sw * a00
        v12 = sw * a10
        u13 = sw * a01
        v13 = sw * a11
        u14 = sw * gu2
        v14 = sw * gv2
        g0 += u0 * ruw
        h0_0 += u0 * u0
        h0_2 += u0 * u2
        h0_4 += u0 * u4
        h0_5 += u0 * u5
        h0_6 += u0 * u6
        h0_7 += u0 * u7
        h0_9 += u0 * u9
        h0_10 += u0 * u10
        h0_11 += u0 * u11
        h0_12 += u0 * u12
        h0_13 += u0 * u13
        h0_14 += u0 * u14
        g1 += v1 * rvw
        h1_1 += v1 * v1
        h1_3 += v1 * v3
        h1_4 += v1 * v4
        h1_5 += v1 * v5
        h1_6 += v1 * v6
        h1_7 += v1 * v7
        h1_9 += v1 * v9
        h1_10 += v1 * v10
        h1_11 += v1 * v11
        h1_12 += v1 * v12
        h1_13 += v1 * v13
        h1_14 += v1 * v14
        g2 += u2 * ruw
        h2_2 += u2 * u2
        h2_4 += u2 * u4
        h2_5 += u2 * u5
        h2_6 += u2 * u6
        h2_7 += u2 * u7
        h2_9 += u2 * u9
        h2_10 += u2 * u10
        h2_11 += u2 * u11
        h2_12 += u2 * u12
        h2_13 += u2 * u13
        h2_14 += u2 * u14
        g3 += v3 * rvw
        h3_3 += v3 * v3
        h3_4 += v3 * v4
        h3_5 += v3 * v5
        h3_6 += v3 * v6
        h3_7 += v3 * v7
        h3_9 += v3 * v9
        h3_10 += v3 * v10
        h3_11 += v3 * v11
        h3_12 += v3 * v12
        h3_13 += v3 * v13
        h3_14 += v3 * v14
        g4 += u4 * ruw + v4 * rvw
        h4_4 += u4 * u4 + v4 * v4
        h4_5 += u4 * u5 + v4 * v5
        h4_6 += u4 * u6 + v4 * v6
        h4_7 += u4 * u7 + v4 * v7
        h4_9 += u4 * u9 + v4 * v9
        h4_10 += u4 * u10 + v4 * v10
        h4_11 += u4 * u11 + v4 * v11
        h4_12 += u4 * u12 + v4 * v12
        h4_13 += u4 * u13 + v4 * v13
        h4_14 += u4 * u14 + v4 * v14
        g5 += u5 * ruw + v5 * rvw
        h5_5 += u5 * u5 + v5 * v5
        h5_6 += u5 * u6 + v5 * v6
        h5_7 += u5 * u7 + v5 * v7
        h5_9 += u5 * u9 + v5 * v9
        h5_10 += u5 * u10 + v5 * v10
        h5_11 += u5 * u11 + v5 * v11
        h5_12 += u5 * u12 + v5 * v12
        h5_13 += u5 * u13 + v5 * v13
        h5_14 += u5 * u14 + v5 * v14
        g6 += u6 * ruw + v6 * rvw
        h6_6 += u6 * u6 + v6 * v6
        h6_7 += u6 * u7 + v6 * v7
        h6_9 += u6 * u9 + v6 * v9
        h6_10 += u6 * u10 + v6 * v10
        h6_11 += u6 * u11 + v6 * v11
        h6_12 += u6 * u12 + v6 * v12
        h6_13 += u6 * u13 + v6 * v13
        h6_14 += u6 * u14 + v6 * v14
        g7 += u7 * ruw + v7 * rvw
        h7_7 += u7 * u7 + v7 * v7
        h7_9 += u7 * u9 + v7 * v9
        h7_10 += u7 * u10 + v7 * v10
        h7_11 += u7 * u11 + v7 * v11
        h7_12 += u7 * u12 + v7 * v12
        h7_13 += u7 * u13 + v7 * v13
        h7_14 += u7 * u14 + v7 * v14
        g9 += u9 * ruw + v9 * rvw
        h9_9 += u9 * u9 + v9 * v9
        h9_10 += u9 * u10 + v9 * v10
        h9_11 += u9 * u11 + v9 * v11
        h9_12 += u9 * u12 + v9 * v12
        h9_13 += u9 * u13 + v9 * v13
        h9_14 += u9 * u14 + v9 * v14
        g10 += u10 * ruw + v10 * rvw
        h10_10 += u10 * u10 + v10 * v10
        h10_11 += u10 * u11 + v10 * v11
        h10_12 += u10 * u12 + v10 * v12
        h10_13 += u10 * u13 + v10 * v13
        h10_14 += u10 * u14 + v10 * v14
        g11 += u11 * ruw + v11 * rvw
        h11_11 += u11 * u11 + v11 * v11
        h11_12 += u11 * u12 + v11 * v12
        h11_13 += u11 * u13 + v11 * v13
        h11_14 += u11 * u14 + v11 * v14
        g12 += u12 * ruw + v12 * rvw
        h12_12 += u12 * u12 + v12 * v12
        h12_13 += u12 * u13 + v12 * v13
        h12_14 += u12 * u14 + v12 * v14
        g13 += u13 * ruw + v13 * rvw
        h13_13 += u13 * u13 + v13 * v13
        h13_14 += u13 * u14 + v13 * v14
        g14 += u14 * ruw + v14 * rvw
        h14_14 += u14 * u14 + v14 * v14
    g[0] = g0
    H[0, 0], H[0, 1], H[0, 2], H[0, 3], H[0, 4], H[0, 5] = h0_0, 0.0, h0_2, 0.0, h0_4, h0_5
    H[0, 6], H[0, 7], H[0, 8], H[0, 9], H[0, 10], H[0, 11] = h0_6, h0_7, 0.0, h0_9, h0_10, h0_11
    H[0, 12], H[0, 13], H[0, 14] = h0_12, h0_13, h0_14
    g[1] = g1
    H[1, 1], H[1, 2], H[1, 3], H[1, 4], H[1, 5], H[1, 6] = h1_1, 0.0, h1_3, h1_4, h1_5, h1_6
    H[1, 7], H[1, 8], H[1, 9], H[1, 10], H[1, 11], H[1, 12] = h1_7, 0.0, h1_9, h1_10, h1_11, h1_12
    H[1, 13], H[1, 14] = h1_13, h1_14
    g[2] = g2
    H[2, 2], H[2, 3], H[2, 4], H[2, 5], H[2, 6], H[2, 7] = h2_2, 0.0, h2_4, h2_5, h2_6, h2_7
    H[2, 8], H[2, 9], H[2, 10], H[2, 11], H[2, 12], H[2, 13] = 0.0, h2_9, h2_10, h2_11, h2_12, h2_13
    H[2, 14] = h2_14
    g[3] = g3
    H[3, 3], H[3, 4], H[3, 5], H[3, 6], H[3, 7], H[3, 8] = h3_3, h3_4, h3_5, h3_6, h3_7, 0.0
    H[3, 9], H[3, 10], H[3, 11], H[3, 12], H[3, 13], H[3, 14] = h3_9, h3_10, h3_11, h3_12, h3_13, h3_14
    g[4] = g4
    H[4, 4], H[4, 5], H[4, 6], H[4, 7], H[4, 8], H[4, 9] = h4_4, h4_5, h4_6, h4_7, 0.0, h4_9
    H[4, 10], H[4, 11], H[4, 12], H[4, 13], H[4, 14] = h4_10, h4_11, h4_12, h4_13, h4_14
    g[5] = g5
    H[5, 5], H[5, 6], H[5, 7], H[5, 8], H[5, 9], H[5, 10] = h5_5, h5_6, h5_7, 0.0, h5_9, h5_10
    H[5, 11], H[5, 12], H[5, 13], H[5, 14] = h5_11, h5_12, h5_13, h5_14
    g[6] = g6
    H[6, 6], H[6, 7], H[6, 8], H[6, 9], H[6, 10], H[6, 11] = h6_6, h6_7, 0.0, h6_9, h6_10, h6_11
    H[6, 12], H[6, 13], H[6, 14] = h6_12, h6_13, h6_14
    g[7] = g7
    H[7, 7], H[7, 8], H[7, 9], H[7, 10], H[7, 11], H[7, 12] = h7_7, 0.0, h7_9, h7_10, h7_11, h7_12
    H[7, 13], H[7, 14] = h7_13, h7_14
    g[8] = 0.0
    H[8, 8], H[8, 9], H[8, 10], H[8, 11], H[8, 12], H[8, 13] = 0.0, 0.0, 0.0, 0.0, 0.0, 0.0
    H[8, 14] = 0.0
    g[9] = g9
    H[9, 9], H[9, 10], H[9, 11], H[9, 12], H[9, 13], H[9, 14] = h9_9, h9_10, h9_11, h9_12, h9_13, h9_14
    g[10] = g10
    H[10, 10], H[10, 11], H[10, 12], H[10, 13], H[10, 14] = h10_10, h10_11, h10_12, h10_13, h10_14
    g[11] = g11
    H[11, 11], H[11, 12], H[11, 13], H[11, 14] = h11_11, h11_12, h11_13, h11_14
    g[12] = g12
    H[12, 12], H[12, 13], H[12, 14] = h12_12, h12_13, h12_14
    g[13] = g13
    H[13, 13], H[13, 14] = h13_13, h13_14
    g[14] = g14
    H[14, 14] = h14_14
    for a in range(15):  # the lower triangle mirrors the upper
        for b in range(a):
            H[a, b] = H[b, a]
    return cost


@njit(cache=True, fastmath=True, nogil=True, error_model="numpy")
def jacobian_15(
    intr: np.ndarray,  # (4,)
    dist: np.ndarray,  # (5,)
    R: np.ndarray,  # (3, 3)
    t: np.ndarray,  # (3,)
    X: np.ndarray,  # (3, N) world x, y, z of every point, one row per coordinate
    Ju: np.ndarray,  # (15, N) out: d(u)/d(parameter) at every point
    Jv: np.ndarray,  # (15, N) out: d(v)/d(parameter)
) -> None:
    """The pixels' Jacobian itself, by parameter row (the algebra of :func:`normal_equations_15`, unweighted): for the Monte-Carlo's first step, formed once per call."""
    fx, fy = intr[0], intr[1]
    k1, k2, p1, p2, k3 = dist[0], dist[1], dist[2], dist[3], dist[4]
    r00, r01, r02, r10, r11, r12, r20, r21, r22 = R[0, 0], R[0, 1], R[0, 2], R[1, 0], R[1, 1], R[1, 2], R[2, 0], R[2, 1], R[2, 2]
    t0, t1, t2 = t[0], t[1], t[2]
    for n in range(X.shape[1]):
        X0, X1, X2 = X[0, n], X[1, n], X[2, n]
        ax = r00 * X0 + r01 * X1 + r02 * X2
        ay = r10 * X0 + r11 * X1 + r12 * X2
        az = r20 * X0 + r21 * X1 + r22 * X2
        iz = 1.0 / (az + t2)
        xn = (ax + t0) * iz
        yn = (ay + t1) * iz
        r2 = xn * xn + yn * yn
        r4 = r2 * r2
        radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
        xy2 = 2.0 * xn * yn
        drad = k1 + r2 * (2.0 * k2 + 3.0 * k3 * r2)
        dxd_dy = xy2 * drad + 2.0 * p1 * xn + 2.0 * p2 * yn
        a00 = fx * (radial + 2.0 * xn * xn * drad + 2.0 * p1 * yn + 6.0 * p2 * xn) * iz
        a01 = fx * dxd_dy * iz
        a10 = fy * dxd_dy * iz
        a11 = fy * (radial + 2.0 * yn * yn * drad + 6.0 * p1 * yn + 2.0 * p2 * xn) * iz
        gu2 = -(a00 * xn + a01 * yn)
        gv2 = -(a10 * xn + a11 * yn)
        Ju[0, n], Jv[0, n] = xn * radial + p1 * xy2 + p2 * (r2 + 2.0 * xn * xn), 0.0
        Ju[1, n], Jv[1, n] = 0.0, yn * radial + p1 * (r2 + 2.0 * yn * yn) + p2 * xy2
        Ju[2, n], Jv[2, n] = 1.0, 0.0
        Ju[3, n], Jv[3, n] = 0.0, 1.0
        Ju[4, n], Jv[4, n] = fx * xn * r2, fy * yn * r2
        Ju[5, n], Jv[5, n] = fx * xn * r4, fy * yn * r4
        Ju[6, n], Jv[6, n] = fx * xy2, fy * (r2 + 2.0 * yn * yn)
        Ju[7, n], Jv[7, n] = fx * (r2 + 2.0 * xn * xn), fy * xy2
        Ju[8, n], Jv[8, n] = fx * xn * r4 * r2, fy * yn * r4 * r2
        Ju[9, n], Jv[9, n] = ay * gu2 - az * a01, ay * gv2 - az * a11
        Ju[10, n], Jv[10, n] = az * a00 - ax * gu2, az * a10 - ax * gv2
        Ju[11, n], Jv[11, n] = ax * a01 - ay * a00, ax * a11 - ay * a10
        Ju[12, n], Jv[12, n] = a00, a10
        Ju[13, n], Jv[13, n] = a01, a11
        Ju[14, n], Jv[14, n] = gu2, gv2
