"""Smooth 6-dof trajectories with closed-form derivatives, the truth behind simulated flights.

Why closed form: a simulated IMU must be the exact derivative of the truth, so that an
estimator's error comes only from the noise we add on purpose, never from differentiating
coarse samples. Every trajectory here yields, at any time, the position and its first two
derivatives and Z-Y-X Euler angles with their first derivative; the body rate follows from the
Euler rates, the specific force from the acceleration (:class:`Kinematics`).

Two ways to build one:
- :class:`EulerTrajectory`: position and Euler angles as enveloped sums of sinusoids
  (:class:`SineMotion`), e.g. a sensor platform waved by a robot arm.
- :class:`ThrustAlignedTrajectory`: a path of segments (:class:`SegmentPath`: hold, smooth move,
  speed ramp, turn) flown by a helicopter whose body down axis follows its thrust, i.e. the
  direction of ``g_W - a_W``, with the nose on the path heading.
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from dataclasses import dataclass, field
from math import comb
from typing import Protocol

import numpy as np
from numpy.polynomial import Polynomial

from vtolpose.estimator.core.rotation import quat_from_euler, quat_to_rot

# Degree-9 smoothstep: 0 -> 1 on [0, 1], four derivatives vanish at both ends, so joining
# segments with it keeps the path C^4 and hence the body rate C^1 (RK4 integrates it cleanly).
SMOOTHSTEP = Polynomial([0, 0, 0, 0, 0, 126, -420, 540, -315, 70])
_SMOOTHSTEP_DERIVS = [SMOOTHSTEP] + [SMOOTHSTEP.deriv(k) for k in range(1, 5)]
_SMOOTHSTEP_INTEGRAL = SMOOTHSTEP.integ()
_GAUSS_X, _GAUSS_W = np.polynomial.legendre.leggauss(24)


def smoothstep(x: np.ndarray, order: int = 0) -> np.ndarray:
    """``order``-th derivative (in x) of the smoothstep, held at 0 before 0 and 1 after 1."""
    x = np.asarray(x, dtype=float)
    value = _SMOOTHSTEP_DERIVS[order](np.clip(x, 0.0, 1.0))
    if order == 0:
        return np.where(x <= 0.0, 0.0, np.where(x >= 1.0, 1.0, value))
    return np.where((x > 0.0) & (x < 1.0), value, 0.0)


@dataclass(frozen=True, slots=True)
class Kinematics:
    """Truth at times ``t`` [s from start]: world NED ``p, v, a`` and Z-Y-X Euler angles."""

    t: np.ndarray
    p: np.ndarray
    v: np.ndarray
    a: np.ndarray
    euler: np.ndarray
    euler_rate: np.ndarray

    def q(self) -> np.ndarray:
        """Body→NED quaternions [w, x, y, z], shape (N, 4)."""
        return np.asarray(quat_from_euler(*self.euler.T)).T.reshape(-1, 4)

    def rotation(self) -> np.ndarray:
        """Body→NED rotation matrices, shape (N, 3, 3)."""
        return quat_to_rot(self.q())

    def omega_b(self) -> np.ndarray:
        """Body angular rate [rad/s] from the Euler rates (Z-Y-X kinematics, exact)."""
        roll, pitch, _ = self.euler.T
        droll, dpitch, dyaw = self.euler_rate.T
        sr, cr, sp, cp = np.sin(roll), np.cos(roll), np.sin(pitch), np.cos(pitch)
        return np.stack(
            [droll - dyaw * sp, dpitch * cr + dyaw * cp * sr, -dpitch * sr + dyaw * cp * cr], axis=-1
        )

    def specific_force_b(self, gravity: float) -> np.ndarray:
        """What an ideal accelerometer reads: ``R^T (a_W - g_W)`` with ``g_W = [0, 0, +g]``."""
        f_w = self.a - np.array([0.0, 0.0, gravity])
        return np.einsum("nji,nj->ni", self.rotation(), f_w)


class Trajectory(Protocol):
    """Anything that gives exact kinematics at arbitrary times (seconds from the start)."""

    def kinematics(self, t: np.ndarray) -> Kinematics: ...


@dataclass(frozen=True, slots=True)
class SineMotion:
    """``centre + E(t) * sum_k A_k sin(w_k (t - start) + phase_k)`` per axis.

    ``E`` ramps from 0 to 1 with the smoothstep over ``ramp_s`` after ``start_s``, so the
    motion leaves the static start without a jump in any derivative up to the fourth.
    Arrays ``amplitude``, ``angular_freq`` and ``phase`` are (3, K).
    """

    centre: np.ndarray
    amplitude: np.ndarray
    angular_freq: np.ndarray
    phase: np.ndarray
    start_s: float
    ramp_s: float

    def derivatives(self, t: np.ndarray, order: int) -> list[np.ndarray]:
        """``[x, x', ..., x^(order)]``, each (N, 3), by the product rule on envelope × sines."""
        tau = np.asarray(t, dtype=float)[:, None, None] - self.start_s
        x = tau / self.ramp_s
        envelope = [smoothstep(x, i)[..., 0, 0] / self.ramp_s**i for i in range(order + 1)]
        angle = self.angular_freq * tau + self.phase
        sines = [
            np.sum(self.amplitude * self.angular_freq**k * np.sin(angle + 0.5 * np.pi * k), axis=-1)
            for k in range(order + 1)
        ]
        out = []
        for k in range(order + 1):
            value = sum(comb(k, i) * envelope[i][:, None] * sines[k - i] for i in range(k + 1))
            out.append(value + (self.centre if k == 0 else 0.0))
        return out


@dataclass(frozen=True, slots=True)
class EulerTrajectory:
    """Position and attitude as independent smooth signals (a robot arm can do any pose)."""

    position: SineMotion
    attitude: SineMotion

    def kinematics(self, t: np.ndarray) -> Kinematics:
        t = np.asarray(t, dtype=float)
        p, v, a = self.position.derivatives(t, 2)
        euler, euler_rate = self.attitude.derivatives(t, 1)
        return Kinematics(t, p, v, a, euler, euler_rate)


@dataclass(frozen=True, slots=True)
class PathSample:
    """World NED position and three derivatives, plus heading and its rate, at N times."""

    p: np.ndarray
    v: np.ndarray
    a: np.ndarray
    jerk: np.ndarray
    heading: np.ndarray
    heading_rate: np.ndarray

    @classmethod
    def empty(cls, n: int) -> "PathSample":
        return cls(*(np.zeros((n, 3)) for _ in range(4)), np.zeros(n), np.zeros(n))

    def put(self, mask: np.ndarray, part: "PathSample") -> None:
        for name in ("p", "v", "a", "jerk", "heading", "heading_rate"):
            getattr(self, name)[mask] = getattr(part, name)


def _unit(heading: np.ndarray) -> np.ndarray:
    heading = np.asarray(heading, dtype=float)
    return np.stack([np.cos(heading), np.sin(heading), np.zeros_like(heading)], axis=-1)


@dataclass(frozen=True, slots=True)
class Segment(ABC):
    """One piece of a path, sampled at local times ``tau`` in [0, duration_s]."""

    label: str
    duration_s: float
    start: np.ndarray
    heading: float

    @abstractmethod
    def sample(self, tau: np.ndarray) -> PathSample:
        """Path values at local times ``tau`` (seconds since the segment began)."""

    def end(self) -> tuple[np.ndarray, float]:
        """Position and heading where the next segment must start."""
        last = self.sample(np.array([self.duration_s]))
        return last.p[0], float(last.heading[0])

    def _constant_heading(self, p: np.ndarray, v: np.ndarray, a: np.ndarray, jerk: np.ndarray) -> PathSample:
        n = len(p)
        return PathSample(p, v, a, jerk, np.full(n, self.heading), np.zeros(n))


@dataclass(frozen=True, slots=True)
class Hold(Segment):
    """Standing still (on the ground, or hovering)."""

    def sample(self, tau: np.ndarray) -> PathSample:
        n = len(tau)
        zeros = np.zeros((n, 3))
        return self._constant_heading(np.tile(self.start, (n, 1)), zeros, zeros, zeros.copy())


@dataclass(frozen=True, slots=True)
class SmoothMove(Segment):
    """Rest to rest by ``delta`` [m] along a smoothstep (e.g. a vertical climb)."""

    delta: np.ndarray = field(default_factory=lambda: np.zeros(3))

    def sample(self, tau: np.ndarray) -> PathSample:
        x = np.asarray(tau, dtype=float) / self.duration_s
        d = [smoothstep(x, k)[:, None] / self.duration_s**k * self.delta for k in range(4)]
        return self._constant_heading(self.start + d[0], d[1], d[2], d[3])


@dataclass(frozen=True, slots=True)
class AlongTrack(Segment):
    """Straight flight along ``heading``, speed going smoothly from ``speed0`` to ``speed1``."""

    speed0: float = 0.0
    speed1: float = 0.0

    def sample(self, tau: np.ndarray) -> PathSample:
        tau = np.asarray(tau, dtype=float)
        x = tau / self.duration_s
        dv, T = self.speed1 - self.speed0, self.duration_s
        dist = self.speed0 * tau + dv * T * _SMOOTHSTEP_INTEGRAL(x)
        along = [dist, self.speed0 + dv * smoothstep(x), dv * smoothstep(x, 1) / T, dv * smoothstep(x, 2) / T**2]
        u = _unit(self.heading)
        return self._constant_heading(self.start + along[0][:, None] * u, *(s[:, None] * u for s in along[1:]))


@dataclass(frozen=True, slots=True)
class Turn(Segment):
    """Level turn at constant ``speed``; the heading changes by ``turn_rad`` along a smoothstep.

    Velocity, acceleration and jerk are closed form; the position is the integral of the
    velocity by 24-point Gauss-Legendre quadrature, exact to rounding for this smooth integrand.
    """

    speed: float = 0.0
    turn_rad: float = 0.0

    def _heading(self, tau: np.ndarray, order: int) -> np.ndarray:
        value = self.turn_rad * smoothstep(tau / self.duration_s, order) / self.duration_s**order
        return value + (self.heading if order == 0 else 0.0)

    def sample(self, tau: np.ndarray) -> PathSample:
        tau = np.asarray(tau, dtype=float)
        h, dh, ddh = (self._heading(tau, k) for k in range(3))
        nodes = 0.5 * tau[:, None] * (_GAUSS_X + 1.0)
        integral = 0.5 * tau[:, None] * np.einsum("nkd,k->nd", _unit(self._heading(nodes, 0)), _GAUSS_W)
        along, rightward = _unit(h), _unit(h + 0.5 * np.pi)
        v = self.speed * along
        a = self.speed * dh[:, None] * rightward
        jerk = self.speed * (ddh[:, None] * rightward - dh[:, None] ** 2 * along)
        return PathSample(self.start + self.speed * integral, v, a, jerk, h, dh)


def turn_sidestep(turn_rad: float) -> float:
    """Sideways displacement of a :class:`Turn` per metre of ``speed * duration``.

    ``∫_0^1 sin(turn_rad S(x)) dx``; for a half turn (π) it is about 0.32, which sets how long a
    turn takes to move the aircraft over to the next survey lane.
    """
    x = 0.5 * (_GAUSS_X + 1.0)
    return float(0.5 * np.sum(_GAUSS_W * np.sin(turn_rad * SMOOTHSTEP(x))))


@dataclass(frozen=True, slots=True)
class SegmentPath:
    """Segments flown one after the other from t = 0; sampling past the end is an error."""

    segments: tuple[Segment, ...]

    @property
    def starts(self) -> np.ndarray:
        return np.concatenate([[0.0], np.cumsum([s.duration_s for s in self.segments])])

    @property
    def duration_s(self) -> float:
        return float(self.starts[-1])

    def _index(self, t: np.ndarray) -> np.ndarray:
        t = np.asarray(t, dtype=float)
        if t.size and (t.min() < 0.0 or t.max() > self.duration_s):
            raise ValueError(f"path covers 0..{self.duration_s:.3f} s, asked for {t.min():.3f}..{t.max():.3f} s")
        return np.clip(np.searchsorted(self.starts, t, side="right") - 1, 0, len(self.segments) - 1)

    def sample(self, t: np.ndarray) -> PathSample:
        t = np.asarray(t, dtype=float)
        index = self._index(t)
        out = PathSample.empty(len(t))
        starts = self.starts
        for i in np.unique(index):
            mask = index == i
            out.put(mask, self.segments[i].sample(t[mask] - starts[i]))
        return out

    def labels(self, t: np.ndarray) -> np.ndarray:
        """Segment label at each time ("static", "climb", "leg", "turn", ...)."""
        return np.array([s.label for s in self.segments])[self._index(t)]


@dataclass(frozen=True, slots=True)
class ThrustAlignedTrajectory:
    """A helicopter on a path: body down axis along ``g_W - a_W``, nose on the path heading.

    With ``n = g_W - a_W`` seen in the heading frame, ``m = Rz(-heading) n``, the Z-Y-X angles
    are ``pitch = atan2(m_x, m_z)`` and ``roll = atan2(-m_y, hypot(m_x, m_z))``; their rates
    follow from ``m' = Rz(-heading) (-jerk) + heading' * dRz(-heading)/dheading n``.
    """

    path: SegmentPath
    gravity: float

    def kinematics(self, t: np.ndarray) -> Kinematics:
        t = np.asarray(t, dtype=float)
        s = self.path.sample(t)
        c, si = np.cos(s.heading), np.sin(s.heading)
        n = np.array([0.0, 0.0, self.gravity]) - s.a
        dn = -s.jerk
        m = np.stack([c * n[:, 0] + si * n[:, 1], -si * n[:, 0] + c * n[:, 1], n[:, 2]], axis=-1)
        dm = np.stack(
            [
                c * dn[:, 0] + si * dn[:, 1] + s.heading_rate * (-si * n[:, 0] + c * n[:, 1]),
                -si * dn[:, 0] + c * dn[:, 1] - s.heading_rate * (c * n[:, 0] + si * n[:, 1]),
                dn[:, 2],
            ],
            axis=-1,
        )
        mx, my, mz = m.T
        dmx, dmy, dmz = dm.T
        rho = np.hypot(mx, mz)
        drho = (mx * dmx + mz * dmz) / rho
        pitch, dpitch = np.arctan2(mx, mz), (mz * dmx - mx * dmz) / rho**2
        roll, droll = np.arctan2(-my, rho), (my * drho - rho * dmy) / (rho**2 + my**2)
        euler = np.stack([roll, pitch, s.heading], axis=-1)
        euler_rate = np.stack([droll, dpitch, s.heading_rate], axis=-1)
        return Kinematics(t, s.p, s.v, s.a, euler, euler_rate)
