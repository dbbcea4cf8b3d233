"""IMU time update (thesis eq. 4.1) on the nominal state and the error-state covariance.

One step integrates the mean of two consecutive IMU samples over ``dt`` (second-order
accurate for smooth motion), rotates the specific force with the half-step attitude, and
propagates only the robot rows and columns of the covariance, so a step costs O(n) in the
map size, not O(n²). The analytic Jacobian :func:`error_transition` is tested against
central differences of :func:`integrate_nominal`.
"""

from __future__ import annotations

import math

import numpy as np

from estimator.calibration import ImuNoise
from estimator.state import FilterState, StateLayout


def _skew(x: float, y: float, z: float) -> np.ndarray:
    return np.array([[0.0, -z, y], [z, 0.0, -x], [-y, x, 0.0]])


def _rotvec_to_rot(phi: np.ndarray) -> np.ndarray:
    """Rodrigues' formula with a series for small angles (the common case at IMU rate)."""
    angle2 = float(phi @ phi)
    k = _skew(phi[0], phi[1], phi[2])
    if angle2 < 1e-10:
        return np.eye(3) + k + 0.5 * (k @ k)
    angle = math.sqrt(angle2)
    return np.eye(3) + (math.sin(angle) / angle) * k + ((1.0 - math.cos(angle)) / angle2) * (k @ k)


def _right_jacobian(phi: np.ndarray) -> np.ndarray:
    """Right Jacobian of SO(3): ``Exp(φ + δ) ≈ Exp(φ) Exp(Jr(φ) δ)``."""
    angle2 = float(phi @ phi)
    k = _skew(phi[0], phi[1], phi[2])
    if angle2 < 1e-10:
        return np.eye(3) - 0.5 * k + (1.0 / 6.0) * (k @ k)
    angle = math.sqrt(angle2)
    return np.eye(3) - ((1.0 - math.cos(angle)) / angle2) * k + ((angle - math.sin(angle)) / (angle2 * angle)) * (k @ k)


def _quat_to_rot(q: np.ndarray) -> np.ndarray:
    w, x, y, z = q
    return np.array(
        [
            [1.0 - 2.0 * (y * y + z * z), 2.0 * (x * y - w * z), 2.0 * (x * z + w * y)],
            [2.0 * (x * y + w * z), 1.0 - 2.0 * (x * x + z * z), 2.0 * (y * z - w * x)],
            [2.0 * (x * z - w * y), 2.0 * (y * z + w * x), 1.0 - 2.0 * (x * x + y * y)],
        ]
    )


def _quat_times_rotvec(q: np.ndarray, phi: np.ndarray) -> np.ndarray:
    """``q ⊗ Exp(φ)`` normalised: the body-frame attitude increment."""
    angle = math.sqrt(float(phi @ phi))
    half = 0.5 * angle
    s = math.sin(half) / angle if angle > 1e-9 else 0.5 - angle * angle / 48.0
    dw, dx, dy, dz = math.cos(half), s * phi[0], s * phi[1], s * phi[2]
    w, x, y, z = q
    out = np.array(
        [
            w * dw - x * dx - y * dy - z * dz,
            w * dx + x * dw + y * dz - z * dy,
            w * dy - x * dz + y * dw + z * dx,
            w * dz + x * dy - y * dx + z * dw,
        ]
    )
    return out / math.sqrt(float(out @ out))


def integrate_nominal(
    p: np.ndarray,
    v: np.ndarray,
    q: np.ndarray,
    b_g: np.ndarray,
    b_a: np.ndarray,
    gyro: np.ndarray,
    accel: np.ndarray,
    dt: float,
    gravity: np.ndarray,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """One nominal step with mean IMU readings ``gyro``/``accel`` (body) over ``dt``.

    Returns ``(p', v', q', a_W)``; ``a_W`` is the world acceleration used (gravity included).
    """
    phi = (gyro - b_g) * dt
    r = _quat_to_rot(q)
    r_half = r @ _rotvec_to_rot(0.5 * phi)
    a_w = r_half @ (accel - b_a) + gravity
    p_new = p + v * dt + (0.5 * dt * dt) * a_w
    v_new = v + a_w * dt
    return p_new, v_new, _quat_times_rotvec(q, phi), a_w


def error_transition(
    q: np.ndarray, b_g: np.ndarray, b_a: np.ndarray, gyro: np.ndarray, accel: np.ndarray, dt: float, layout: StateLayout
) -> np.ndarray:
    """Jacobian F of the robot error state over one step of :func:`integrate_nominal`."""
    n = layout.robot_dim
    phi = (gyro - b_g) * dt
    f = accel - b_a
    r = _quat_to_rot(q)
    r_half = r @ _rotvec_to_rot(0.5 * phi)
    a_skew = _skew(*(r_half @ f))
    F = np.eye(n)
    h2 = 0.5 * dt * dt
    F[0:3, 3:6] = dt * np.eye(3)
    F[0:3, 6:9] = -h2 * a_skew
    F[3:6, 6:9] = -dt * a_skew
    if layout.estimates_biases:
        r_new = r @ _rotvec_to_rot(phi)
        d_a_d_bg = r_half @ _skew(*f) @ _right_jacobian(0.5 * phi) * (0.5 * dt)
        F[0:3, 9:12] = h2 * d_a_d_bg
        F[3:6, 9:12] = dt * d_a_d_bg
        F[6:9, 9:12] = -dt * (r_new @ _right_jacobian(phi))
        F[0:3, 12:15] = -h2 * r_half
        F[3:6, 12:15] = -dt * r_half
    return F


def process_noise(
    q: np.ndarray, dt: float, noise: ImuNoise, layout: StateLayout, extra_horizontal_accel: float = 0.0
) -> np.ndarray:
    """Discrete process noise of one step (white noise held over the step, bias random walks).

    ``extra_horizontal_accel`` [m/s²/√Hz] widens horizontal velocity while the heading is
    unknown, so that the filter follows GPS instead of a mis-rotated accelerometer.
    """
    n = layout.robot_dim
    r = _quat_to_rot(q)
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


class ImuPropagator:
    """Advances a :class:`FilterState` from one IMU sample to the next.

    This is the per-sample hot path (125–200 Hz, and replays run it 100× faster than real
    time), so it computes the rotation quantities once with scalar arithmetic and reuses a
    preallocated transition matrix; :func:`integrate_nominal` and :func:`error_transition`
    are the readable references it is tested against.
    """

    def __init__(self, noise: ImuNoise, gravity: float) -> None:
        self.noise = noise
        self.gravity = np.array([0.0, 0.0, float(gravity)])
        self._isotropic = all(
            np.all(getattr(noise, k) == getattr(noise, k)[0])
            for k in ("gyro_noise_density", "accel_noise_density")
        )
        self._F: np.ndarray | None = None
        self._q_cache: tuple[float, float, StateLayout] | None = None
        self._Q: np.ndarray | None = None

    def _noise(self, q: np.ndarray, dt: float, layout: StateLayout, extra: float) -> np.ndarray:
        if not self._isotropic:
            return process_noise(q, dt, self.noise, layout, extra)
        # Isotropic white noise is invariant under rotation: Q depends on dt alone.
        key = (dt, extra, layout)
        if self._q_cache != key:
            self._Q = process_noise(np.array([1.0, 0.0, 0.0, 0.0]), dt, self.noise, layout, extra)
            self._q_cache = key
        return self._Q

    def propagate(
        self,
        state: FilterState,
        gyro: np.ndarray,
        accel: np.ndarray,
        dt: float,
        extra_horizontal_accel: float = 0.0,
    ) -> np.ndarray:
        """Propagate nominal state and covariance by ``dt`` with mean readings; returns ``a_W``."""
        lay = state.layout
        n = lay.robot_dim
        Q = self._noise(state.q, dt, lay, extra_horizontal_accel)
        w, x, y, z = state.q.tolist()
        gx, gy, gz = ((gyro - state.b_g) * dt).tolist()
        fx, fy, fz = (accel - state.b_a).tolist()
        angle = math.sqrt(gx * gx + gy * gy + gz * gz)
        # Half-step and full-step attitude increments as quaternions.
        if angle > 1e-9:
            sh, sf = math.sin(0.25 * angle) / angle, math.sin(0.5 * angle) / angle
        else:
            sh, sf = 0.25, 0.5
        ch, cf = math.cos(0.25 * angle), math.cos(0.5 * angle)
        hw, hx, hy, hz = _qmul(w, x, y, z, ch, sh * gx, sh * gy, sh * gz)
        nw, nx, ny, nz = _qmul(w, x, y, z, cf, sf * gx, sf * gy, sf * gz)
        norm = 1.0 / math.sqrt(nw * nw + nx * nx + ny * ny + nz * nz)
        r_half = _rot(hw, hx, hy, hz)
        ax = r_half[0][0] * fx + r_half[0][1] * fy + r_half[0][2] * fz
        ay = r_half[1][0] * fx + r_half[1][1] * fy + r_half[1][2] * fz
        az = r_half[2][0] * fx + r_half[2][1] * fy + r_half[2][2] * fz
        a_w = np.array([ax, ay, az + self.gravity[2]])
        state.p = state.p + state.v * dt + (0.5 * dt * dt) * a_w
        state.v = state.v + a_w * dt
        state.q = np.array([nw * norm, nx * norm, ny * norm, nz * norm])

        F = self._F
        if F is None or F.shape[0] != n:
            F = self._F = np.eye(n)
        F[0:3, 3:6] = np.eye(3) * dt
        h2 = 0.5 * dt * dt
        a_skew = np.array([[0.0, -az, ay], [az, 0.0, -ax], [-ay, ax, 0.0]])
        F[0:3, 6:9] = a_skew * -h2
        F[3:6, 6:9] = a_skew * -dt
        if lay.estimates_biases:
            rh = np.array(r_half)
            d_a_d_bg = rh @ _skew(fx, fy, fz) @ np.array(_jr(0.5 * gx, 0.5 * gy, 0.5 * gz)) * (0.5 * dt)
            F[0:3, 9:12] = d_a_d_bg * h2
            F[3:6, 9:12] = d_a_d_bg * dt
            F[6:9, 9:12] = (np.array(_rot(nw * norm, nx * norm, ny * norm, nz * norm)) @ np.array(_jr(gx, gy, gz))) * -dt
            F[0:3, 12:15] = rh * -h2
            F[3:6, 12:15] = rh * -dt
        cov = state.cov
        if cov.shape[0] == n:
            state.cov = F @ cov @ F.T + Q
        else:
            cov[:n, :n] = F @ cov[:n, :n] @ F.T + Q
            cross = F @ cov[:n, n:]
            cov[:n, n:] = cross
            cov[n:, :n] = cross.T
        return a_w


def _qmul(w, x, y, z, dw, dx, dy, dz):
    return (
        w * dw - x * dx - y * dy - z * dz,
        w * dx + x * dw + y * dz - z * dy,
        w * dy - x * dz + y * dw + z * dx,
        w * dz + x * dy - y * dx + z * dw,
    )


def _jr(x, y, z):
    """Right Jacobian of SO(3) at φ = (x, y, z) as nested tuples (see :func:`_right_jacobian`)."""
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


def _rot(w, x, y, z):
    return (
        (1.0 - 2.0 * (y * y + z * z), 2.0 * (x * y - w * z), 2.0 * (x * z + w * y)),
        (2.0 * (x * y + w * z), 1.0 - 2.0 * (x * x + z * z), 2.0 * (y * z - w * x)),
        (2.0 * (x * z - w * y), 2.0 * (y * z + w * x), 1.0 - 2.0 * (x * x + y * y)),
    )
