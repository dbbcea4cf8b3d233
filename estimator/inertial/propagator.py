"""IMU time update (thesis eq. 4.1) on the nominal state and the error-state covariance.

One step consumes an :class:`~vtolpose.estimator.inertial.imu_delta.ImuDelta` (delta angle and delta velocity
over ``dt``) and corrects it for the biases to first order:

    φ   = Δθ − b_g dt
    Δv' = Δv − ½ dt (b_g × Δv)                 (the rotation within the step was slower by b_g)
    a_W = R (Δv'/dt − b_a) + g_W
    p'  = p + v dt + ½ a_W dt²,   v' = v + a_W dt,   q' = q ⊗ Exp(φ)

Only the robot rows and columns of the covariance change, so a step costs O(n) in the map
size, not O(n²). :func:`error_transition` is tested against central differences of
:func:`integrate_nominal`; :class:`ImuPropagator` is the fast path, tested against both.
"""

from __future__ import annotations

import math

import numpy as np

from vtolpose.estimator.core.calibration import ImuNoise
from vtolpose.estimator.inertial.imu_delta import ImuDelta
from vtolpose.estimator.core.rotation import rot_of as _rot, rotvec_quat
from vtolpose.estimator.core.state import FilterState, StateLayout


def _skew(x: float, y: float, z: float) -> np.ndarray:
    return np.array([[0.0, -z, y], [z, 0.0, -x], [-y, x, 0.0]])


def _jr(x: float, y: float, z: float) -> tuple:
    """Right Jacobian of SO(3) at φ = (x, y, z): ``Exp(φ + δ) ≈ Exp(φ) Exp(Jr(φ) δ)``."""
    t2 = x * x + y * y + z * z
    if t2 < 1e-10:
        a, b = 0.5, 1.0 / 6.0
    else:
        t = math.sqrt(t2)
        a, b = (1.0 - math.cos(t)) / t2, (t - math.sin(t)) / (t2 * t)
    # Jr = I - a [φ]x + b [φ]x², with [φ]x² = φ φ^T - |φ|² I.
    return (
        (1.0 + b * (x * x - t2), a * z + b * x * y, -a * y + b * x * z),
        (-a * z + b * x * y, 1.0 + b * (y * y - t2), a * x + b * y * z),
        (a * y + b * x * z, -a * x + b * y * z, 1.0 + b * (z * z - t2)),
    )


def _quat_times_rotvec(q: np.ndarray, phi: np.ndarray) -> np.ndarray:
    """``q ⊗ Exp(φ)``, normalised: the body-frame attitude increment."""
    dw, dx, dy, dz = rotvec_quat(*phi.tolist())
    w, x, y, z = q.tolist()
    out = np.array(
        [
            w * dw - x * dx - y * dy - z * dz,
            w * dx + x * dw + y * dz - z * dy,
            w * dy - x * dz + y * dw + z * dx,
            w * dz + x * dy - y * dx + z * dw,
        ]
    )
    return out / math.sqrt(float(out @ out))


def _corrected(b_g: np.ndarray, b_a: np.ndarray, dtheta: np.ndarray, dvel: np.ndarray, dt: float):
    """Bias-corrected rotation vector and mean specific force (start-of-step body frame)."""
    phi = dtheta - b_g * dt
    dv = dvel - (0.5 * dt) * np.cross(b_g, dvel)
    return phi, dv / dt - b_a


def integrate_nominal(
    p: np.ndarray,
    v: np.ndarray,
    q: np.ndarray,
    b_g: np.ndarray,
    b_a: np.ndarray,
    dtheta: np.ndarray,
    dvel: np.ndarray,
    dt: float,
    gravity: np.ndarray,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """One nominal step over an IMU delta. Returns ``(p', v', q', a_W)``."""
    phi, f = _corrected(b_g, b_a, dtheta, dvel, dt)
    a_w = np.array(_rot(*q.tolist())) @ f + gravity
    return p + v * dt + (0.5 * dt * dt) * a_w, v + a_w * dt, _quat_times_rotvec(q, phi), a_w


def error_transition(
    q: np.ndarray, b_g: np.ndarray, b_a: np.ndarray, dtheta: np.ndarray, dvel: np.ndarray, dt: float, layout: StateLayout
) -> np.ndarray:
    """Jacobian F of the robot error state (global attitude error) over one step."""
    n = layout.robot_dim
    phi, f = _corrected(b_g, b_a, dtheta, dvel, dt)
    r = np.array(_rot(*q.tolist()))
    a_skew = _skew(*(r @ f))
    F = np.eye(n)
    h2 = 0.5 * dt * dt
    F[0:3, 3:6] = dt * np.eye(3)
    F[0:3, 6:9] = -h2 * a_skew
    F[3:6, 6:9] = -dt * a_skew
    if layout.estimates_biases:
        r_new = np.array(_rot(*_quat_times_rotvec(q, phi).tolist()))
        d_a_d_bg = 0.5 * (r @ _skew(*dvel))
        F[0:3, 9:12] = h2 * d_a_d_bg
        F[3:6, 9:12] = dt * d_a_d_bg
        F[6:9, 9:12] = -dt * (r_new @ np.array(_jr(*phi.tolist())))
        F[0:3, 12:15] = -h2 * r
        F[3:6, 12:15] = -dt * r
    return F


def process_noise(
    q: np.ndarray, dt: float, noise: ImuNoise, layout: StateLayout, extra_horizontal_accel: float = 0.0
) -> np.ndarray:
    """Discrete process noise of one step (white noise held over the step, bias random walks).

    ``extra_horizontal_accel`` [m/s²/√Hz] widens horizontal velocity while the heading is
    unknown, so that the filter follows GPS instead of a mis-rotated accelerometer.
    """
    n = layout.robot_dim
    r = np.array(_rot(*q.tolist()))
    sig_a = (r * noise.accel_noise_density**2) @ r.T
    if extra_horizontal_accel > 0.0:
        sig_a[0, 0] += extra_horizontal_accel**2
        sig_a[1, 1] += extra_horizontal_accel**2
    Q = np.zeros((n, n))
    Q[0:3, 0:3] = sig_a * (0.25 * dt**3)
    Q[0:3, 3:6] = sig_a * (0.5 * dt**2)
    Q[3:6, 0:3] = Q[0:3, 3:6]
    Q[3:6, 3:6] = sig_a * dt
    Q[6:9, 6:9] = ((r * noise.gyro_noise_density**2) @ r.T) * dt
    if layout.estimates_biases:
        Q[9:12, 9:12] = np.diag(noise.gyro_random_walk**2 * dt)
        Q[12:15, 12:15] = np.diag(noise.accel_random_walk**2 * dt)
    return Q


def is_isotropic(noise: ImuNoise) -> bool:
    """The same white-noise density on every axis: Q is then invariant under rotation."""
    return all(np.all(np.asarray(x) == np.asarray(x).flat[0]) for x in (noise.gyro_noise_density, noise.accel_noise_density))


def noise_dt_polynomial(noise: ImuNoise, layout: StateLayout, extra: float = 0.0) -> tuple[np.ndarray, ...]:
    """``(A, B, C)`` with Q(dt) = A dt + B dt² + C dt³ for isotropic noise, solved from dt = 1, 2, 3."""
    identity = np.array([1.0, 0.0, 0.0, 0.0])
    q1, q2, q3 = (process_noise(identity, x, noise, layout, extra) for x in (1.0, 2.0, 3.0))
    c3 = (q3 - 3.0 * q2 + 3.0 * q1) / 6.0
    c2 = (q2 - 2.0 * q1) / 2.0 - 3.0 * c3
    return q1 - c2 - c3, c2, c3


class ImuPropagator:
    """Advances a :class:`FilterState` by one IMU delta.

    The per-step hot path: rotation quantities are computed once with scalar arithmetic and
    written into a preallocated transition matrix with one indexed assignment; the blocks that
    depend only on ``dt`` (and the process noise) are rewritten only when ``dt`` changes.
    """

    def __init__(self, noise: ImuNoise, gravity: float) -> None:
        self.noise = noise
        self.gravity = np.array([0.0, 0.0, float(gravity)])
        self._g = float(gravity)
        self._isotropic = is_isotropic(noise)
        self._F: np.ndarray | None = None
        self._eye3 = np.eye(3)
        # Per layout (the heading bank's members carry biases while the filter may not, and they
        # alternate): [F, flat view of F, the dt its constant blocks hold]; and Q's polynomial terms
        # with the last (dt, extra², Q).
        self._transitions: dict[str, list] = {}
        self._q_terms: dict[str, tuple] = {}
        self._q_last: dict[str, tuple[float, float, np.ndarray]] = {}

    @property
    def transition(self) -> np.ndarray | None:
        """The robot error-state transition F of the last :meth:`propagate` (overwritten by the next)."""
        return self._F

    def _noise(self, q: np.ndarray, dt: float, layout: StateLayout, extra: float) -> np.ndarray:
        if not self._isotropic:
            return process_noise(q, dt, self.noise, layout, extra)
        # Isotropic white noise is invariant under rotation, and each block of Q is a power of
        # dt times a constant: keep the constant matrices, combine them per step. Q is linear in
        # extra² (it adds to the horizontal accelerometer variance): Q = Q(0) + extra² (Q(1) − Q(0)),
        # so a heading still unknown (extra changing every step) costs no refit.
        key = layout.variant
        terms = self._q_terms.get(key)
        if terms is None:
            base, unit = (noise_dt_polynomial(self.noise, layout, x) for x in (0.0, 1.0))
            terms = self._q_terms[key] = (base, tuple(u - b for u, b in zip(unit, base)))
        e2 = extra * extra
        last = self._q_last.get(key)
        if last is not None and last[0] == dt and last[1] == e2:  # a steady IMU rate: the same Q again
            return last[2]
        base, per_extra2 = terms
        c1, c2, c3 = (b + e2 * d for b, d in zip(base, per_extra2)) if e2 else base
        Q = (c1 + (c2 + c3 * dt) * dt) * dt
        self._q_last[key] = (dt, e2, Q)
        return Q

    def _transition(self, layout: StateLayout, dt: float) -> tuple[np.ndarray, np.ndarray]:
        """The preallocated F of ``layout`` with its dt-only blocks written for ``dt``, and its flat view."""
        held = self._transitions.get(layout.variant)
        if held is None:
            F = np.eye(layout.robot_dim)
            held = self._transitions[layout.variant] = [F, F.reshape(-1), math.nan]
        F = held[0]
        if dt != held[2]:
            F[0:3, 3:6] = self._eye3 * dt
            held[2] = dt
        self._F = F
        return F, held[1]

    def propagate(self, state: FilterState, delta: ImuDelta, extra_horizontal_accel: float = 0.0) -> np.ndarray:
        """Propagate nominal state and covariance over ``delta``; returns ``a_W``."""
        lay = state.layout
        n = lay.robot_dim
        dt = delta.dt
        Q = self._noise(state.q, dt, lay, extra_horizontal_accel)
        w, x, y, z = state.q.tolist()
        bgx, bgy, bgz = state.b_g.tolist()
        tx, ty, tz = delta.dtheta.tolist()
        px, py, pz = tx - bgx * dt, ty - bgy * dt, tz - bgz * dt
        vx, vy, vz = delta.dvel.tolist()
        # Δv corrected for the slower rotation, then the mean specific force minus b_a.
        h = 0.5 * dt
        cx, cy, cz = bgy * vz - bgz * vy, bgz * vx - bgx * vz, bgx * vy - bgy * vx
        bax, bay, baz = state.b_a.tolist()
        fx, fy, fz = (vx - h * cx) / dt - bax, (vy - h * cy) / dt - bay, (vz - h * cz) / dt - baz
        r = _rot(w, x, y, z)
        (r00, r01, r02), (r10, r11, r12), (r20, r21, r22) = r
        ax = r00 * fx + r01 * fy + r02 * fz
        ay = r10 * fx + r11 * fy + r12 * fz
        sz = r20 * fx + r21 * fy + r22 * fz  # the specific force's z, before gravity
        az = sz + self._g
        h2 = 0.5 * dt * dt
        p0x, p0y, p0z = state.p.tolist()
        v0x, v0y, v0z = state.v.tolist()
        state.p = np.array([p0x + v0x * dt + h2 * ax, p0y + v0y * dt + h2 * ay, p0z + v0z * dt + h2 * az])
        state.v = np.array([v0x + ax * dt, v0y + ay * dt, v0z + az * dt])
        dw, dx, dy, dz = rotvec_quat(px, py, pz)
        nw = w * dw - x * dx - y * dy - z * dz
        nx = w * dx + x * dw + y * dz - z * dy
        ny = w * dy - x * dz + y * dw + z * dx
        nz = w * dz + x * dy - y * dx + z * dw
        norm = 1.0 / math.sqrt(nw * nw + nx * nx + ny * ny + nz * nz)
        nw, nx, ny, nz = nw * norm, nx * norm, ny * norm, nz * norm
        state.q = np.array([nw, nx, ny, nz])

        F, F_flat = self._transition(lay, dt)
        # −[R f]× scaled by ½dt² (position) and dt (velocity), in the attitude columns.
        values = [sz * h2, -ay * h2, -sz * h2, ax * h2, ay * h2, -ax * h2,
                  sz * dt, -ay * dt, -sz * dt, ax * dt, ay * dt, -ax * dt]
        if lay.estimates_biases:
            # ∂a/∂b_g = ½ R [Δv]×, the attitude's −dt R(q') Jr(φ), the accelerometer bias's −R.
            hx, hy, hz = 0.5 * vx, 0.5 * vy, 0.5 * vz
            d = ((r01 * hz - r02 * hy, r02 * hx - r00 * hz, r00 * hy - r01 * hx),
                 (r11 * hz - r12 * hy, r12 * hx - r10 * hz, r10 * hy - r11 * hx),
                 (r21 * hz - r22 * hy, r22 * hx - r20 * hz, r20 * hy - r21 * hx))
            rn, jr = _rot(nw, nx, ny, nz), _jr(px, py, pz)
            m = -dt
            values += [e * h2 for row in d for e in row]
            values += [e * dt for row in d for e in row]
            values += [(a[0] * jr[0][j] + a[1] * jr[1][j] + a[2] * jr[2][j]) * m for a in rn for j in range(3)]
            values += [e * -h2 for row in r for e in row]
            values += [e * m for row in r for e in row]
        F_flat[_transition_index(n, lay.estimates_biases)] = values
        cov = state.cov
        if cov.shape[0] == n:
            state.cov = F @ cov @ F.T + Q
        else:
            cov[:n, :n] = F @ cov[:n, :n] @ F.T + Q
            cross = F @ cov[:n, n:]
            cov[:n, n:] = cross
            cov[n:, :n] = cross.T
        return np.array([ax, ay, az])


_INDEX_CACHE: dict[tuple[int, bool], np.ndarray] = {}


def _transition_index(n: int, biases: bool) -> np.ndarray:
    """Flat indices of F's state-dependent entries, in the order :meth:`ImuPropagator.propagate` lists them."""
    key = (n, biases)
    index = _INDEX_CACHE.get(key)
    if index is None:
        skew = [(0, 1), (0, 2), (1, 0), (1, 2), (2, 0), (2, 1)]  # nonzero entries of a 3 × 3 skew matrix
        cells = [(r, 6 + c) for r, c in skew] + [(3 + r, 6 + c) for r, c in skew]
        if biases:
            for row0, col0 in ((0, 9), (3, 9), (6, 9), (0, 12), (3, 12)):
                cells += [(row0 + i, col0 + j) for i in range(3) for j in range(3)]
        index = _INDEX_CACHE[key] = np.array([r * n + c for r, c in cells], dtype=np.intp)
    return index
