"""One filter step (nominal state, transition F, covariance) compiled to machine code.

The step runs 60–100 times per second of data, once more for each heading hypothesis while the
heading is searched for, and in Python its ~150 scalar operations cost more than the 15 × 15
matrix products. Compiled with numba it takes a quarter of the time. It is the one implementation
of the step; tests hold it to the same equations written plainly (tests/propagation_oracle.py, itself
tested against central differences), and to its own interpreted run (``step.py_func``) bit for bit.
Its rotations are ``core.rotation``'s primitives, compiled.

Compiled once per machine and cached next to this file (or where ``NUMBA_CACHE_DIR`` says); a
process loads the cached code on first use, which the runtime does before its first sample
(``service.runtime.kernels.load_compiled_kernels``).
"""

from __future__ import annotations

import math

import numba
import numpy as np

from vtolpose.estimator.core.rotation import compiled_quat_product as quat_product
from vtolpose.estimator.core.rotation import compiled_right_jacobian_of as right_jacobian_of
from vtolpose.estimator.core.rotation import compiled_rot_of as rot_of
from vtolpose.estimator.core.rotation import compiled_rotvec_quat as rotvec_quat

OUT_LEN = 13  # p (3), v (3), q (4), a_W (3)


@numba.njit(cache=True, nogil=True)
def rotation(w: float, x: float, y: float, z: float, r: np.ndarray) -> None:
    """``r`` ← R(q) for a unit quaternion (w first): ``rotation.rot_of`` written into an array."""
    (r[0, 0], r[0, 1], r[0, 2]), (r[1, 0], r[1, 1], r[1, 2]), (r[2, 0], r[2, 1], r[2, 2]) = rot_of(w, x, y, z)


@numba.njit(cache=True, nogil=True)
def step(p: np.ndarray, v: np.ndarray, q: np.ndarray, b_g: np.ndarray, b_a: np.ndarray, dtheta: np.ndarray,
          dvel: np.ndarray, dt: float, gravity: float, F: np.ndarray, cov: np.ndarray, Q: np.ndarray,
          biases: bool, out: np.ndarray) -> np.ndarray:
    """One step over a delta (see ``propagator``'s module docstring for the equations).

    Writes the new p, v, q and a_W into ``out``, the state-dependent entries of ``F`` (its constant
    ones, identity and zeros, are the caller's), and returns ``F cov Fᵀ + Q`` for the robot block.
    """
    w, x, y, z = q[0], q[1], q[2], q[3]
    px, py, pz = dtheta[0] - b_g[0] * dt, dtheta[1] - b_g[1] * dt, dtheta[2] - b_g[2] * dt
    vx, vy, vz = dvel[0], dvel[1], dvel[2]
    # Δv corrected for the slower rotation, then the mean specific force minus b_a.
    h = 0.5 * dt
    cx, cy, cz = b_g[1] * vz - b_g[2] * vy, b_g[2] * vx - b_g[0] * vz, b_g[0] * vy - b_g[1] * vx
    fx, fy, fz = (vx - h * cx) / dt - b_a[0], (vy - h * cy) / dt - b_a[1], (vz - h * cz) / dt - b_a[2]
    r = np.empty((3, 3))
    rotation(w, x, y, z, r)
    ax = r[0, 0] * fx + r[0, 1] * fy + r[0, 2] * fz
    ay = r[1, 0] * fx + r[1, 1] * fy + r[1, 2] * fz
    sz = r[2, 0] * fx + r[2, 1] * fy + r[2, 2] * fz  # the specific force's z, before gravity
    az = sz + gravity
    h2 = 0.5 * dt * dt
    out[0] = p[0] + v[0] * dt + h2 * ax
    out[1] = p[1] + v[1] * dt + h2 * ay
    out[2] = p[2] + v[2] * dt + h2 * az
    out[3] = v[0] + ax * dt
    out[4] = v[1] + ay * dt
    out[5] = v[2] + az * dt
    dw, dx, dy, dz = rotvec_quat(px, py, pz)
    nw, nx, ny, nz = quat_product(w, x, y, z, dw, dx, dy, dz)
    norm = 1.0 / math.sqrt(nw * nw + nx * nx + ny * ny + nz * nz)
    nw, nx, ny, nz = nw * norm, nx * norm, ny * norm, nz * norm
    out[6], out[7], out[8], out[9] = nw, nx, ny, nz
    out[10], out[11], out[12] = ax, ay, az

    # Position from velocity; −[R f]× scaled by ½dt² (position) and dt (velocity) in the attitude columns.
    for i in range(3):
        F[i, 3 + i] = dt
    F[0, 7], F[0, 8], F[1, 6], F[1, 8], F[2, 6], F[2, 7] = sz * h2, -ay * h2, -sz * h2, ax * h2, ay * h2, -ax * h2
    F[3, 7], F[3, 8], F[4, 6], F[4, 8], F[5, 6], F[5, 7] = sz * dt, -ay * dt, -sz * dt, ax * dt, ay * dt, -ax * dt
    if biases:
        # ∂a/∂b_g = ½ R [Δv]×, the attitude's −dt R(q') Jr(φ), the accelerometer bias's −R.
        hx, hy, hz = 0.5 * vx, 0.5 * vy, 0.5 * vz
        rn = np.empty((3, 3))
        rotation(nw, nx, ny, nz, rn)
        jr = np.empty((3, 3))
        (jr[0, 0], jr[0, 1], jr[0, 2]), (jr[1, 0], jr[1, 1], jr[1, 2]), (jr[2, 0], jr[2, 1], jr[2, 2]) = \
            right_jacobian_of(px, py, pz)
        m = -dt
        for i in range(3):
            d0 = r[i, 1] * hz - r[i, 2] * hy
            d1 = r[i, 2] * hx - r[i, 0] * hz
            d2 = r[i, 0] * hy - r[i, 1] * hx
            F[i, 9], F[i, 10], F[i, 11] = d0 * h2, d1 * h2, d2 * h2
            F[3 + i, 9], F[3 + i, 10], F[3 + i, 11] = d0 * dt, d1 * dt, d2 * dt
            for j in range(3):
                F[6 + i, 9 + j] = (rn[i, 0] * jr[0, j] + rn[i, 1] * jr[1, j] + rn[i, 2] * jr[2, j]) * m
                F[i, 12 + j] = r[i, j] * -h2
                F[3 + i, 12 + j] = r[i, j] * m
    return F @ cov @ F.T + Q


@numba.njit(cache=True, nogil=True)
def noise_from_terms(terms: np.ndarray, extra2: float, dt: float) -> np.ndarray:
    """Q = (c1 + (c2 + c3 dt) dt) dt with c_k = base_k + extra² Δ_k (``terms`` stacks base_1..3 then Δ_1..3):
    the isotropic process noise of ``propagator``, element by element in the same order. Written as whole-array
    arithmetic, which compiles to the same element-wise operations and runs as a few numpy calls when the
    kernels are interpreted (a cold cache) instead of a Python loop over 225 elements."""
    c1, c2, c3 = terms[0], terms[1], terms[2]
    if extra2 != 0.0:
        c1, c2, c3 = c1 + extra2 * terms[3], c2 + extra2 * terms[4], c3 + extra2 * terms[5]
    return (c1 + (c2 + c3 * dt) * dt) * dt


@numba.njit(cache=True, nogil=True)
def step_run(p: np.ndarray, v: np.ndarray, q: np.ndarray, b_g: np.ndarray, b_a: np.ndarray, deltas: np.ndarray,
             dts: np.ndarray, gravity: float, F: np.ndarray, cov: np.ndarray, terms: np.ndarray, biases: bool,
             horizontal: np.ndarray, average_s: float, unaligned: bool, floor: float,
             at_rest: np.ndarray, start_row: bool) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """:func:`step` for each of a sequence of deltas (rows of [Δθ, Δv]), with the isotropic noise of each
    ``dt`` (:func:`noise_from_terms`) and the filter's running mean of the horizontal acceleration, from
    ``horizontal`` on: what the interpreted loop of steps does, in the same order.

    ``unaligned``: the heading is unknown, and each step's noise has the extra horizontal accelerometer
    noise the filter adds then, ``max(floor, 2 |mean − at_rest|)`` from the mean before the step
    (``Estimator._propagate``). Returns, after each step, p, v, q (rows of 10), the robot
    covariance, and that mean (rows of 2); with ``start_row``, the state before the first step as their
    first row (a pose owed before the steps goes out with theirs).
    """
    m = dts.shape[0]
    n = cov.shape[0]
    o = 1 if start_row else 0
    states = np.empty((m + o, 10))
    covs = np.empty((m + o, n, n))
    means = np.empty((m + o, 2))
    out = np.empty(OUT_LEN)
    hx, hy = horizontal[0], horizontal[1]
    if start_row:
        states[0, 0:3], states[0, 3:6], states[0, 6:10] = p, v, q
        covs[0] = cov
        means[0, 0], means[0, 1] = hx, hy
    for j in range(m):
        dt = dts[j]
        extra2 = 0.0
        if unaligned:
            ax, ay = hx - at_rest[0], hy - at_rest[1]
            extra = max(floor, 2.0 * math.sqrt(ax * ax + ay * ay))
            extra2 = extra * extra
        Q = noise_from_terms(terms, extra2, dt)
        cov = step(p, v, q, b_g, b_a, deltas[j, 0:3], deltas[j, 3:6], dt, gravity, F, cov, Q, biases, out)
        covs[j + o] = cov
        states[j + o] = out[0:10]
        p, v, q = states[j + o, 0:3], states[j + o, 3:6], states[j + o, 6:10]
        keep = average_s / (average_s + dt)
        hx, hy = keep * hx + (1.0 - keep) * out[10], keep * hy + (1.0 - keep) * out[11]
        means[j + o, 0], means[j + o, 1] = hx, hy
    return states, covs, means


@numba.njit(cache=True, nogil=True)
def step_all(p: np.ndarray, v: np.ndarray, q: np.ndarray, b_g: np.ndarray, b_a: np.ndarray, dtheta: np.ndarray,
             dvel: np.ndarray, dt: float, gravity: float, F: np.ndarray, covs: np.ndarray, Q: np.ndarray,
             biases: bool) -> tuple[np.ndarray, np.ndarray]:
    """:func:`step` over one delta for each of several states (rows of ``p``, ``v``, ``q``, ``b_g``, ``b_a``;
    covariances stacked in ``covs``) with the same Q: the heading hypotheses. Returns p, v, q (rows of 10)
    and the covariance of each; ``F`` is left as the last state's."""
    h = p.shape[0]
    states = np.empty((h, 10))
    grown = np.empty_like(covs)
    out = np.empty(OUT_LEN)
    for k in range(h):
        grown[k] = step(p[k], v[k], q[k], b_g[k], b_a[k], dtheta, dvel, dt, gravity, F, covs[k], Q, biases, out)
        states[k] = out[0:10]
    return states, grown


@numba.njit(cache=True, nogil=True)
def step_all_run(p: np.ndarray, v: np.ndarray, q: np.ndarray, b_g: np.ndarray, b_a: np.ndarray, deltas: np.ndarray,
                 dts: np.ndarray, gravity: float, F: np.ndarray, covs: np.ndarray, terms: np.ndarray,
                 biases: bool) -> tuple[np.ndarray, np.ndarray]:
    """:func:`step_all` over each of a sequence of deltas (rows of [Δθ, Δv]) in turn, each with the isotropic
    noise of its ``dt`` (:func:`noise_from_terms`, no extra noise): the heading hypotheses through a run.
    Returns p, v, q (rows of 10) and the covariance of each state after the last delta."""
    h = p.shape[0]
    states = np.empty((h, 10))
    for k in range(h):
        states[k, 0:3], states[k, 3:6], states[k, 6:10] = p[k], v[k], q[k]
    for j in range(dts.shape[0]):
        Q = noise_from_terms(terms, 0.0, dts[j])
        states, covs = step_all(np.ascontiguousarray(states[:, 0:3]), np.ascontiguousarray(states[:, 3:6]),
                                np.ascontiguousarray(states[:, 6:10]), b_g, b_a, np.ascontiguousarray(deltas[j, 0:3]),
                                np.ascontiguousarray(deltas[j, 3:6]), dts[j], gravity, F, covs, Q, biases)
    return states, covs


def warm_up(runs: bool = True) -> None:
    """Compile the kernels, or load them from the cache, now rather than on the first IMU step (which
    would then take a second): each once per layout, on the argument types the filter passes. ``runs``:
    also the sequences of steps (``step_run``, ``step_all_run``), which only a process fusing runs (a
    replay) calls."""
    for n in (9, 15):
        v3 = np.zeros(3)
        step(v3, v3, np.array([1.0, 0.0, 0.0, 0.0]), v3, v3, v3, v3, 0.01, 9.8, np.eye(n), np.eye(n), np.eye(n),
             n == 15, np.empty(OUT_LEN))
        noise_from_terms(np.zeros((6, n, n)), 0.25, 0.01)
        rows = np.zeros((2, 3))
        step_all(rows, rows, np.array([[1.0, 0.0, 0.0, 0.0]] * 2), rows, rows, v3, v3, 0.01, 9.8, np.eye(n),
                 np.zeros((2, n, n)), np.eye(n), n == 15)
        if runs:
            step_all_run(rows, rows, np.array([[1.0, 0.0, 0.0, 0.0]] * 2), rows, rows, np.zeros((2, 6)),
                         np.full(2, 0.01), 9.8, np.eye(n), np.zeros((2, n, n)), np.zeros((6, n, n)), n == 15)
            step_run(v3, v3, np.array([1.0, 0.0, 0.0, 0.0]), v3, v3, np.zeros((2, 6)), np.full(2, 0.01), 9.8, np.eye(n),
                     np.eye(n), np.zeros((6, n, n)), n == 15, np.zeros(2), 0.5, False, 0.2, np.zeros(2), False)
