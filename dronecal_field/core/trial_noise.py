"""Standard normal draws for the Monte-Carlo, made inside the compiled trial loop.

Every trial has its own stream, fixed by the seed and the trial's index
alone: a trial sees the same noise whatever the chunking, the thread count
or the order the threads take the trials in (numba's own ``np.random`` keeps
one state per thread, so its draws would depend on the schedule). The
stream is SplitMix64 (Steele, Lea and Flood 2014; passes BigCrush), started
at a hash of (seed key, trial index); the normals come from Marsaglia and
Tsang's 256-layer ziggurat (2000), the method numpy's ``standard_normal``
uses: one 64-bit draw and one table compare for 98.5 % of the values,
and those are drawn in a loop that compiles to vector instructions
(:func:`fill_trial_normals`), so a trial's 310 normals cost 0.4 us where
numpy's call, with its Python overhead and the (K, N, 5) buffer it fills,
cost 3 us per trial.

Pure functions on integers and arrays; no global state.
"""

from __future__ import annotations

import functools

import numpy as np
from numba import njit

# SplitMix64's constants: the Weyl increment (2^64 / golden ratio) and the finaliser's multipliers.
_GOLDEN = np.uint64(0x9E3779B97F4A7C15)
_MIX1 = np.uint64(0xBF58476D1CE4E5B9)
_MIX2 = np.uint64(0x94D049BB133111EB)
# A second odd constant spreads trial indices over the 2^64 states before hashing (streams start far apart).
_TRIAL_STRIDE = np.uint64(0xD1B54A32D192ED03)
_S30, _S27, _S31, _S8, _S12, _S11 = (np.uint64(v) for v in (30, 27, 31, 8, 12, 11))
_LOW8, _ONE = np.uint64(0xFF), np.uint64(1)


def _ziggurat_tables(layers: int = 256, r: float = 3.6541528853610088, v: float = 4.92867323399e-3):
    """Layer edges x (layers + 1,), f(x) = exp(-x^2 / 2) at them, accept bounds k (layers,) int64 and widths w (layers,).

    Layer 0 is the base strip [0, r] x [0, f(r)] plus the tail beyond r, area v,
    drawn as a box of width v / f(r); layer i >= 1 is the box [0, x_i] x
    [f(x_i), f(x_{i+1})] of the same area v. A draw m / 2^52 * x_i below
    x_{i+1} lies under the curve for sure (m < k_i): no exp is needed.
    """
    x = np.empty(layers + 1)
    x[1] = r
    x[0] = v / np.exp(-0.5 * r * r)
    for i in range(1, layers - 1):
        x[i + 1] = np.sqrt(-2.0 * np.log(v / x[i] + np.exp(-0.5 * x[i] * x[i])))
    x[layers] = 0.0
    f = np.exp(-0.5 * x * x)
    k = np.floor(2.0**52 * x[1:] / x[:-1]).astype(np.int64)
    w = x[:-1] * 2.0**-52
    return x, f, k, w


_X, _F, _K, _W = _ziggurat_tables()
_R = float(_X[1])


@njit(cache=True, nogil=True, inline="always")
def _mix64(st):
    """SplitMix64's output function of a state (also the trials' state scrambler)."""
    z = (st ^ (st >> _S30)) * _MIX1
    z = (z ^ (z >> _S27)) * _MIX2
    return z ^ (z >> _S31)


@njit(cache=True, nogil=True, inline="always")
def _splitmix(s):
    """(next state, 64 random bits) of SplitMix64."""
    s = s + _GOLDEN
    return s, _mix64(s)


@njit(cache=True, nogil=True, inline="always")
def _unit_open0(bits) -> float:
    """A uniform in (0, 1] from 64 random bits (53 of them), safe for log."""
    return (float(bits >> _S11) + 1.0) * (1.0 / 9007199254740992.0)


@njit(cache=True, nogil=True)
def trial_state(key, trial):
    """The stream state trial ``trial`` (int) of seed key ``key`` (uint64) starts from."""
    return _mix64(key + np.uint64(trial) * _TRIAL_STRIDE)


@njit(cache=True, nogil=True, error_model="numpy")
def standard_normal(s):
    """(next state, one N(0, 1) draw): Marsaglia and Tsang's ziggurat on SplitMix64."""
    while True:
        s, bits = _splitmix(s)
        i = np.int64(bits & _LOW8)
        m = np.int64(bits >> _S12)  # 52 bits of mantissa
        negative = ((bits >> _S8) & _ONE) == _ONE
        x = m * _W[i]
        if m < _K[i]:  # inside the layer's box under the curve: 98.8 % of draws end here
            return s, -x if negative else x
        s, accepted, value = _outside_the_box(s, i, x, negative)
        if accepted:
            return s, value


@njit(cache=True, nogil=True, inline="always")
def _outside_the_box(s, i, x, negative):
    """(next state, accepted, draw) for a proposal ``x`` of layer ``i`` outside its box: layer 0 draws from the tail
    beyond r (Marsaglia 1964), always accepted; any other layer takes the wedge test, refused: fresh draws follow."""
    if i == 0:
        while True:
            s, b1 = _splitmix(s)
            s, b2 = _splitmix(s)
            a = -np.log(_unit_open0(b1)) / _R
            b = -np.log(_unit_open0(b2))
            if b + b > a * a:
                x = _R + a
                return s, True, -x if negative else x
    s, b1 = _splitmix(s)
    y = _F[i] + (_unit_open0(b1) - 2.0**-53) * (_F[i + 1] - _F[i])
    return s, y < np.exp(-0.5 * x * x), -x if negative else x


@njit(cache=True, nogil=True, inline="always")
def _layer(s0, j: int) -> int:
    """The ziggurat layer of the stream's j-th output (its low 8 bits)."""
    return np.int64(_mix64(s0 + np.uint64(j + 1) * _GOLDEN) & _LOW8)


@njit(cache=True, nogil=True, error_model="numpy")
def fill_trial_normals(s0, z: np.ndarray, redraw: np.ndarray) -> None:
    """A trial's N(0, 1) draws z (n,) from its stream state s0, in two passes.

    SplitMix64's j-th output is a function of s0 + (j + 1) * increment alone,
    so the first pass draws every value's 64 bits independently and keeps
    the 98.5 % that land inside their layer's box: a loop with no carried
    state, which compiles to vector instructions (0.4 us for 310 values
    against 0.75 one after the other). The rest (``redraw`` (n,) uint8
    workspace marks them) are drawn in order by :func:`standard_normal`
    from the stream's continuation past the first n outputs.
    """
    n = z.shape[0]
    rejected = 0
    for j in range(n):
        bits = _mix64(s0 + np.uint64(j + 1) * _GOLDEN)
        i = np.int64(bits & _LOW8)
        m = np.int64(bits >> _S12)
        sign = 1.0 - 2.0 * np.float64((bits >> _S8) & _ONE)
        ok = m < _K[i]
        z[j] = m * _W[i] * sign
        redraw[j] = 0 if ok else 1
        rejected += 0 if ok else 1
    if rejected:
        s = s0 + np.uint64(n) * _GOLDEN
        for j in range(n):
            if redraw[j]:
                # the ziggurat's slow path for this proposal (tail, or wedge test), then fresh draws if it is refused
                s, accepted, value = _outside_the_box(s, _layer(s0, j), np.abs(z[j]), z[j] < 0.0)
                if accepted:
                    z[j] = value
                else:
                    s, z[j] = standard_normal(s)


@njit(cache=True, nogil=True)
def fill_standard_normal(s, out: np.ndarray):
    """Fill the C-contiguous array ``out`` in memory order with N(0, 1) draws; returns the next state."""
    flat = out.reshape(-1)
    for j in range(flat.shape[0]):
        s, flat[j] = standard_normal(s)
    return s


@functools.lru_cache(maxsize=256)
def seed_key(seed: int) -> np.uint64:
    """The 64-bit key of a user seed (numpy's SeedSequence hash: nearby seeds give unrelated streams; kept, as it costs up to 0.6 ms cold)."""
    return np.uint64(np.random.SeedSequence(int(seed)).generate_state(1, np.uint64)[0])


def trial_normals(seed: int, trial: int, n_points: int) -> tuple[np.ndarray, np.ndarray]:
    """The draws Monte-Carlo trial ``trial`` of ``seed`` sees: (N, 3) for the world points, then (N, 2) for the pixels.

    Its points are P + Z3 * sigma_3d and its pixels p + Z2 * sigma_2d; for
    replaying a trial outside the engine (the tests' cv2 loop).
    """
    z = np.empty(5 * n_points)
    fill_trial_normals(np.uint64(trial_state(seed_key(seed), np.int64(trial))), z, np.empty(5 * n_points, np.uint8))
    return z[: 3 * n_points].reshape(n_points, 3).copy(), z[3 * n_points :].reshape(n_points, 2).copy()
