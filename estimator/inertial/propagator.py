"""IMU time update (thesis eq. 4.1) on the nominal state and the error-state covariance.

One step consumes an :class:`~vtolpose.estimator.inertial.imu_delta.ImuDelta` (delta angle and delta velocity
over ``dt``) and corrects it for the biases to first order:

    φ   = Δθ − b_g dt
    Δv' = Δv − ½ dt (b_g × Δv)                 (the rotation within the step was slower by b_g)
    a_W = R (Δv'/dt − b_a) + g_W
    p'  = p + v dt + ½ a_W dt²,   v' = v + a_W dt,   q' = q ⊗ Exp(φ)

Only the robot rows and columns of the covariance change, so a step costs O(n) in the map
size, not O(n²). The arithmetic is ``propagation_kernel``'s, compiled; the same equations written plainly
(tests/propagation_oracle.py) are the oracle it is tested against, and those against central differences.
"""

from __future__ import annotations

import numpy as np

from vtolpose.estimator.core.calibration import ImuNoise
from vtolpose.estimator.inertial import propagation_kernel
from vtolpose.estimator.inertial.imu_delta import ImuDelta
from vtolpose.estimator.core.rotation import rot_of as _rot
from vtolpose.estimator.core.state import FilterState, StateLayout, stacked

OUT_LEN = propagation_kernel.OUT_LEN  # what the compiled step writes: p, v, q, a_W


def process_noise(
    q: np.ndarray, dt: float, noise: ImuNoise, layout: StateLayout, extra_horizontal_accel: float = 0.0
) -> np.ndarray:
    """Discrete process noise of one step (white noise held over the step, bias random walks).

    ``extra_horizontal_accel`` [m/s²/√Hz] widens horizontal velocity while the heading is
    unknown, so that the filter follows GPS instead of a mis-rotated accelerometer.

    Not a twin of a kernel: it is the runtime's only Q where the white noise differs between axes (Q then
    turns with the attitude, and the compiled steps, which take Q as polynomial terms in dt, decline), and
    the source of those terms where it does not (:func:`noise_dt_polynomial`).
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


_NO_ACCEL = np.zeros(2)


def _unstack(states: list[FilterState], nominal: np.ndarray, covs: np.ndarray) -> None:
    """Each state takes its row of the compiled call's p, v, q (rows of 10) and its covariance."""
    for state, row, cov in zip(states, nominal, covs):
        state.p, state.v, state.q, state.cov = row[0:3], row[3:6], row[6:10], cov


class ImuPropagator:
    """Advances a :class:`FilterState` by one IMU delta.

    The per-step hot path: one call of the compiled step (``propagation_kernel``), which writes the
    state-dependent entries of a preallocated transition matrix; the process noise is kept while
    ``dt`` and the extra accelerometer noise stay the same.
    """

    def __init__(self, noise: ImuNoise, gravity: float) -> None:
        self.noise = noise
        self.gravity = np.array([0.0, 0.0, float(gravity)])
        self._g = float(gravity)
        self._isotropic = is_isotropic(noise)
        self._F: np.ndarray | None = None
        # Per layout (the heading bank's members carry biases while the filter may not, and they
        # alternate): F; and Q's polynomial terms with the last (dt, extra², Q).
        self._transitions: dict[str, np.ndarray] = {}
        self._q_terms: dict[str, np.ndarray] = {}  # (6, n, n): the polynomial's base terms, then their change per extra²
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
        e2 = extra * extra
        last = self._q_last.get(key)
        if last is not None and last[0] == dt and last[1] == e2:  # a steady IMU rate: the same Q again
            return last[2]
        Q = propagation_kernel.noise_from_terms(self._noise_terms(layout), e2, dt)  # (c1 + (c2 + c3 dt) dt) dt, c = base + extra² Δ
        self._q_last[key] = (dt, e2, Q)
        return Q

    def _noise_terms(self, layout: StateLayout) -> np.ndarray:
        """Isotropic Q's polynomial terms for ``layout``: (6, n, n), the base terms, then their change per extra²."""
        terms = self._q_terms.get(layout.variant)
        if terms is None:
            base, unit = (noise_dt_polynomial(self.noise, layout, x) for x in (0.0, 1.0))
            terms = self._q_terms[layout.variant] = np.stack([*base, *(u - b for u, b in zip(unit, base))])
        return terms

    def _transition(self, layout: StateLayout) -> np.ndarray:
        """The preallocated F of ``layout``: identity and zeros, its other entries written by every step."""
        F = self._transitions.get(layout.variant)
        if F is None:
            F = self._transitions[layout.variant] = np.eye(layout.robot_dim)
        self._F = F
        return F

    def propagate_steps(self, state: FilterState, deltas: np.ndarray, dts: np.ndarray, horizontal: np.ndarray,
                        average_s: float, unaligned_floor: float | None = None,
                        at_rest: np.ndarray | None = None,
                        start_row: bool = False) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
        """:meth:`propagate` over a sequence of deltas ([Δθ, Δv] rows) in one compiled call, ``state`` itself
        left as it was: p, v, q (rows of 10) and the covariance after each step, and the running mean of the
        horizontal acceleration from ``horizontal`` on (``average_s``, as the filter keeps it). No extra
        noise, or with ``unaligned_floor`` the filter's while the heading is unknown (from that floor, that
        mean and ``at_rest``, see ``propagation_kernel.step_run``). ``start_row``: ``state`` as it is (and that mean)
        as the first row of each. None where only :meth:`propagate` applies: noise that is not isotropic, or a map
        in the state."""
        lay = state.layout
        cov = state.cov
        if not self._isotropic or cov.shape[0] != lay.robot_dim or not cov.flags.c_contiguous:
            return None
        return propagation_kernel.step_run(state.p, state.v, state.q, state.b_g, state.b_a, deltas, dts, self._g,
                                           self._transition(lay), cov, self._noise_terms(lay), lay.estimates_biases,
                                           horizontal, average_s, unaligned_floor is not None,
                                           0.0 if unaligned_floor is None else float(unaligned_floor),
                                           _NO_ACCEL if at_rest is None else at_rest, start_row)

    def propagate_all(self, states: list[FilterState], delta: ImuDelta) -> bool:
        """:meth:`propagate` (no extra noise) of each of ``states`` over the same delta, in one compiled call.
        False, with nothing done, where only :meth:`propagate` applies (see :meth:`_stacked`)."""
        parts = self._stacked(states)
        if parts is None:
            return False
        layout = states[0].layout
        Q = self._noise(states[0].q, delta.dt, layout, 0.0)
        _unstack(states, *propagation_kernel.step_all(*parts[:5], delta.dtheta, delta.dvel, delta.dt, self._g,
                                                      self._transition(layout), parts[5], Q, layout.estimates_biases))
        return True

    def propagate_all_run(self, states: list[FilterState], deltas: np.ndarray, dts: np.ndarray) -> bool:
        """:meth:`propagate_all` over each of a sequence of deltas ([Δθ, Δv] rows) in turn, in one compiled
        call; False, with nothing done, where :meth:`propagate_all` would decline."""
        parts = self._stacked(states)
        if parts is None:
            return False
        layout = states[0].layout
        _unstack(states, *propagation_kernel.step_all_run(*parts[:5], deltas, dts, self._g, self._transition(layout),
                                                          parts[5], self._noise_terms(layout), layout.estimates_biases))
        return True

    def _stacked(self, states: list[FilterState]) -> tuple[np.ndarray, ...] | None:
        """p, v, q, b_g, b_a and the covariances of ``states`` stacked for the compiled calls; None where they
        cannot go together: noise that is not isotropic (its Q depends on each attitude), a map in a state,
        or states of different layouts."""
        layout = states[0].layout
        n = layout.robot_dim
        if not self._isotropic or any(s.layout != layout or s.cov.shape[0] != n for s in states):
            return None
        return stacked(states)

    def propagate(self, state: FilterState, delta: ImuDelta, extra_horizontal_accel: float = 0.0) -> np.ndarray:
        """Propagate nominal state and covariance over ``delta``; returns ``a_W``.

        The arithmetic is :func:`~vtolpose.estimator.inertial.propagation_kernel.step`, compiled; only
        the robot rows and columns of the covariance change (the map's cross terms through F).
        """
        lay = state.layout
        n = lay.robot_dim
        Q = self._noise(state.q, delta.dt, lay, extra_horizontal_accel)
        F = self._transition(lay)
        out = np.empty(OUT_LEN)
        cov = state.cov
        # The step is compiled for C-ordered arrays; anything else would compile it again, mid-flight.
        robot = cov if cov.shape[0] == n and cov.flags.c_contiguous else np.ascontiguousarray(cov[:n, :n])
        grown = propagation_kernel.step(state.p, state.v, state.q, state.b_g, state.b_a, delta.dtheta, delta.dvel, delta.dt,
                               self._g, F, robot, Q, lay.estimates_biases, out)
        state.p, state.v, state.q = out[0:3], out[3:6], out[6:10]
        if cov.shape[0] == n:
            state.cov = grown
        else:
            cov[:n, :n] = grown
            cross = F @ cov[:n, n:]
            cov[:n, n:] = cross
            cov[n:, :n] = cross.T
        return out[10:13]
