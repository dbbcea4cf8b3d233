"""GPS calibration (thesis 5.4): the receiver's time offset and the antenna lever arm.

Both come from the in-motion alignment model (``vtolpose.estimator.inertial.motion_alignment``): over a window
of a few seconds the fixes must follow

    p(τ) = p0 + v0 τ + ½ g_W τ² + R0 [ S(τ; b_g) − M(τ; b_g) b_a + ΔR(τ; b_g) l ]

with τ the fix's time on the IMU clock. A fix stamped late by L seconds puts its position at
the wrong τ; the window's residual is smallest when the stamps are shifted by −L. So the offset
is found by scanning: for each candidate, shift every fix, refit each window (warm-started from
the neighbouring candidate) and sum the normalised residuals. The curvature of that sum at its
minimum gives the offset's sharpness. The lever arm ``l`` enters linearly and only through the
rotation ΔR: it is fitted jointly over all windows at the chosen offset.

Windows are taken where the IMU's specific force varies most: an offset shows only where the
acceleration changes, a lever arm only where the vehicle turns.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np

from vtolpose.estimator.inertial.imu_delta import ImuDelta, ImuDownsampler
from vtolpose.estimator.inertial.motion_alignment import MotionAligner, MotionAlignOptions, integrate
from vtolpose.estimator.core.rotation import quat_to_rot, so3_exp

LEVER_ARM = slice(-3, None)  # the fit's last three parameters

MOTION_ADVICE = (
    "record the vehicle moving with accelerations that change within seconds (starts and stops, back-and-forth "
    "sweeps, turns; carried by hand is enough) for a minute or more, with GPS fixes arriving throughout")
ROTATION_ADVICE = (
    "record turns: yaw swings of 90 degrees or more and tilts of 10-20 degrees about both horizontal axes, "
    "with GPS fixes arriving throughout (the lever arm shows only when the antenna swings around the IMU)")


class GpsCalibrationError(ValueError):
    """The record cannot give the asked figure; the message says what to record instead."""


@dataclass(frozen=True, slots=True)
class GpsCalibOptions:
    window_s: float = 7.0
    windows: int = 7
    min_windows: int = 3
    min_excitation: float = 0.3  # m/s²: scatter of the specific force a window needs
    max_offset_s: float = 0.3  # scan range ± around ``centre_s``
    centre_s: float = 0.0
    step_s: float = 0.01
    max_sigma_offset_s: float = 0.01
    max_sigma_lever_m: float = 0.03
    filter_rate_hz: float = 100.0
    iterations: int = 20
    sigma_gyro_bias: float = 0.1  # rad/s prior, as the in-motion alignment's
    sigma_accel_bias: float = 0.2  # m/s²


@dataclass(slots=True)
class _Window:
    T0_ns: int  # first IMU boundary; τ is measured from here
    t: np.ndarray  # n + 1 delta boundaries [s]
    dtheta: np.ndarray
    dvel: np.ndarray
    deltas: list[ImuDelta]
    fix_t_ns: np.ndarray
    fix_p: np.ndarray
    fix_sigma: np.ndarray  # (K, 3)
    excitation: float


@dataclass(slots=True)
class _State:
    p0: np.ndarray
    v0: np.ndarray
    R0: np.ndarray
    b_g: np.ndarray
    b_a: np.ndarray

    def moved(self, dx: np.ndarray) -> "_State":
        return _State(self.p0 + dx[0:3], self.v0 + dx[3:6], so3_exp(dx[6:9]) @ self.R0, self.b_g + dx[9:12], self.b_a + dx[12:15])


@dataclass(frozen=True, slots=True)
class LatencyScan:
    """The offset (added to fix stamps to put them on the IMU clock) and how sharply it shows."""

    offsets_s: np.ndarray
    cost: np.ndarray  # Σ squared normalised fix residuals at each offset, all windows
    window_cost: np.ndarray  # (offsets, windows)
    offset_s: float
    sigma_s: float
    window_offsets_s: np.ndarray  # each window's own best offset
    residual_ratio: float  # RMS normalised residual at the best offset
    windows: list[tuple[int, int]]  # (first fix, last fix) stamps [ns]
    n_fixes: int


@dataclass(frozen=True, slots=True)
class LeverArmFit:
    lever_arm_b: np.ndarray
    sigma_m: np.ndarray
    offset_s: float
    residual_ratio: float
    windows: list[tuple[int, int]]
    n_fixes: int


def _excitation(accel: np.ndarray) -> float:
    return float(np.sqrt(np.sum(np.var(accel, axis=0)))) if len(accel) > 1 else 0.0


def select_windows(
    imu_t_ns: np.ndarray, accel: np.ndarray, fix_t_ns: np.ndarray, options: GpsCalibOptions
) -> list[tuple[int, int, float]]:
    """Non-overlapping windows ``(start_ns, end_ns, excitation)`` with the most varied specific force."""
    w_ns = int(options.window_s * 1e9)
    margin = int((abs(options.centre_s) + options.max_offset_s + 0.1) * 1e9)
    candidates = []
    for start in range(int(fix_t_ns[0]), int(fix_t_ns[-1]) - w_ns + 1, max(w_ns // 4, 1)):
        end = start + w_ns
        fixes = fix_t_ns[(fix_t_ns >= start) & (fix_t_ns < end)]
        if len(fixes) < 10 or fixes[-1] - fixes[0] < 0.8 * w_ns:
            continue
        i0, i1 = np.searchsorted(imu_t_ns, [start - margin, end + margin])
        if imu_t_ns[0] > start - margin or i1 >= len(imu_t_ns):
            continue  # the IMU must cover the window at every offset of the scan
        if np.max(np.diff(imu_t_ns[i0:i1])) > 0.1e9:
            continue
        candidates.append((start, end, _excitation(accel[i0:i1])))
    chosen: list[tuple[int, int, float]] = []
    for start, end, exc in sorted(candidates, key=lambda c: -c[2]):
        if exc < options.min_excitation or len(chosen) == options.windows:
            break
        if all(end <= a or start >= b for a, b, _ in chosen):
            chosen.append((start, end, exc))
    if len(chosen) < options.min_windows:
        best = max((c[2] for c in candidates), default=0.0)
        raise GpsCalibrationError(
            f"too little motion: {len(chosen)} window(s) of {options.window_s:g} s have a specific-force scatter of at "
            f"least {options.min_excitation:g} m/s^2 (the liveliest has {best:.2f}); {options.min_windows} are needed: "
            f"{MOTION_ADVICE}")
    return sorted(chosen)


def _window(imu_t_ns, gyro, accel, fix_t_ns, fix_p, fix_sigma, span, options: GpsCalibOptions) -> _Window:
    start, end, exc = span
    margin = int((abs(options.centre_s) + options.max_offset_s + 0.1) * 1e9)
    i0, i1 = np.searchsorted(imu_t_ns, [start - margin, end + margin])
    sampler = ImuDownsampler(options.filter_rate_hz)
    deltas = [d for k in range(i0, i1) if (d := sampler.add(int(imu_t_ns[k]), gyro[k], accel[k])) is not None]
    T0 = deltas[0].t0_ns
    sel = (fix_t_ns >= start) & (fix_t_ns < end)
    return _Window(
        T0_ns=T0,
        t=np.array([0.0] + [(d.t1_ns - T0) * 1e-9 for d in deltas]),
        dtheta=np.array([d.dtheta for d in deltas]),
        dvel=np.array([d.dvel for d in deltas]),
        deltas=deltas,
        fix_t_ns=fix_t_ns[sel],
        fix_p=fix_p[sel],
        fix_sigma=fix_sigma[sel],
        excitation=exc,
    )


class _Fitter:
    """Gauss–Newton over windows that share the gravity and the lever arm (which may be free)."""

    def __init__(self, gravity: float, options: GpsCalibOptions, gyro_bias_prior: np.ndarray | None) -> None:
        self.g = np.array([0.0, 0.0, gravity])
        self.options = options
        self.bg_prior = np.zeros(3) if gyro_bias_prior is None else np.asarray(gyro_bias_prior, dtype=float)

    def _rows(self, w: _Window, s: _State, lever: np.ndarray, offset: float):
        """Normalised residuals of one window and ∂pred/∂[p0 v0 θ b_g b_a l] (normalised)."""
        tau = (w.fix_t_ns - w.T0_ns) * 1e-9 + offset
        eps = 1e-5
        # The gyro-bias columns are numeric: the bias and three nudged copies, integrated as a batch.
        biases = s.b_g[None, :] + np.vstack([np.zeros(3), eps * np.eye(3)])
        ints = integrate(w.t, w.dtheta, w.dvel, biases, tau)
        body = ints.S - np.einsum("bkij,j->bki", ints.M, s.b_a) + np.einsum("bkij,j->bki", ints.R, lever)
        world = body[0] @ s.R0.T
        pred = s.p0 + np.outer(tau, s.v0) + 0.5 * np.outer(tau**2, self.g) + world
        res = ((w.fix_p - pred) / w.fix_sigma).reshape(-1)
        K = len(tau)
        J = np.zeros((K, 3, 18))
        J[:, :, 0:3] = np.eye(3)
        J[:, :, 3:6] = np.eye(3) * tau[:, None, None]
        J[:, :, 6:9] = np.cross(np.eye(3)[None, :, :], world[:, None, :]).transpose(0, 2, 1)
        J[:, :, 9:12] = ((body[1:] - body[0]) @ s.R0.T).transpose(1, 2, 0) / eps
        J[:, :, 12:15] = -np.einsum("ij,kjl->kil", s.R0, ints.M[0])
        J[:, :, 15:18] = np.einsum("ij,kjl->kil", s.R0, ints.R[0])
        return res, (J / w.fix_sigma[:, :, None]).reshape(3 * K, 18)

    def _system(self, windows, states, lever, offset, free_lever):
        """Stacked residuals (fixes, then bias priors, per window), their Jacobian, fix costs."""
        o = self.options
        W = len(windows)
        n = 15 * W + (3 if free_lever else 0)
        blocks_r, blocks_J, fix_costs = [], [], []
        for i, (w, s) in enumerate(zip(windows, states)):
            r, Jw = self._rows(w, s, lever, offset)
            fix_costs.append(float(r @ r))
            blocks_r.append(np.concatenate([r, (self.bg_prior - s.b_g) / o.sigma_gyro_bias, -s.b_a / o.sigma_accel_bias]))
            J = np.zeros((len(r) + 6, n))
            J[: len(r), 15 * i : 15 * i + 15] = Jw[:, :15]
            if free_lever:
                J[: len(r), 15 * W :] = Jw[:, 15:]
            J[len(r) : len(r) + 3, 15 * i + 9 : 15 * i + 12] = np.eye(3) / o.sigma_gyro_bias
            J[len(r) + 3 :, 15 * i + 12 : 15 * i + 15] = np.eye(3) / o.sigma_accel_bias
            blocks_J.append(J)
        return np.concatenate(blocks_r), np.vstack(blocks_J), fix_costs

    def fit(self, windows, states, lever, offset, free_lever=False):
        """Damped Gauss–Newton; returns (states, lever, per-window fix cost, J, r)."""
        W = len(windows)
        lam = 1e-5
        r, J, fix_costs = self._system(windows, states, lever, offset, free_lever)
        for _ in range(self.options.iterations):
            cost = float(r @ r)
            normal, grad = J.T @ J, J.T @ r
            improved = False
            for _ in range(8):
                dx = np.linalg.solve(normal + lam * np.diag(np.diag(normal) + 1e-12), grad)
                cand = [s.moved(dx[15 * i : 15 * i + 15]) for i, s in enumerate(states)]
                cand_lever = lever + dx[15 * W :] if free_lever else lever
                c_r, c_J, c_costs = self._system(windows, cand, cand_lever, offset, free_lever)
                if float(c_r @ c_r) < cost:
                    states, lever, r, J, fix_costs = cand, cand_lever, c_r, c_J, c_costs
                    lam = max(lam / 10.0, 1e-7)
                    improved = True
                    break
                lam *= 10.0
            if not improved or float(r @ r) > cost - 1e-3:  # converged to a thousandth of a unit of χ²
                break
        return states, lever, fix_costs, J, r

    def initial_state(self, w: _Window, lever: np.ndarray, offset: float) -> _State:
        """The in-motion alignment's solution for the window, moved to its start, then the best of
        the four quarter-turn headings after refinement (a poor first heading is a local minimum)."""
        span = ((w.fix_t_ns[-1] - w.fix_t_ns[0]) * 1e-9)
        opts = MotionAlignOptions(window_s=span + 10.0, min_window_s=span - 1e-6, solve_every_s=1e-6,
                                  max_sigma_tilt_deg=180.0, max_sigma_heading_deg=180.0, max_residual_ratio=1e9)
        aligner = MotionAligner(opts, float(self.g[2]), lever)
        aligner.set_bias_prior(self.bg_prior, self.options.sigma_gyro_bias, np.zeros(3), self.options.sigma_accel_bias)
        for d in w.deltas:
            aligner.add_delta(d)
        shift = int(round(offset * 1e9))
        result = None
        for t, p, sig in zip(w.fix_t_ns, w.fix_p, w.fix_sigma):
            result = aligner.add_fix(int(t) + shift, p, float(sig[0]), float(sig[2])) or result
        if result is None:
            start = _State(w.fix_p[0].copy(), np.zeros(3), np.eye(3), self.bg_prior.copy(), np.zeros(3))
        else:
            tau_e = (result.t_ns - w.T0_ns) * 1e-9
            e = integrate(w.t, w.dtheta, w.dvel, result.gyro_bias, np.array([tau_e]))
            R0 = quat_to_rot(result.q) @ e.R[0].T
            v0 = result.v - self.g * tau_e - R0 @ (e.V[0] - e.MV[0] @ result.accel_bias)
            p0 = result.p - v0 * tau_e - 0.5 * self.g * tau_e**2 - R0 @ (e.S[0] - e.M[0] @ result.accel_bias)
            start = _State(p0, v0, R0, result.gyro_bias.copy(), result.accel_bias.copy())
        best = None
        for quarter in range(4):
            turned = _State(start.p0, start.v0, so3_exp(np.array([0.0, 0.0, quarter * math.pi / 2])) @ start.R0,
                            start.b_g, start.b_a)
            states, _, costs, _, _ = self.fit([w], [turned], lever, offset)
            if best is None or costs[0] < best[1]:
                best = (states[0], costs[0])
            if math.sqrt(best[1] / (3 * len(w.fix_t_ns))) < 3.0:
                break
        return best[0]


def _parabola_min(x: np.ndarray, y: np.ndarray, i: int) -> tuple[float, float]:
    """Vertex and curvature of a parabola through the points around index ``i``."""
    lo, hi = max(0, i - 2), min(len(x), i + 3)
    a2, a1, _ = np.polyfit(x[lo:hi] - x[i], y[lo:hi], 2)
    if a2 <= 0.0:
        return float(x[i]), 0.0
    vertex = -a1 / (2.0 * a2)
    return float(x[i] + np.clip(vertex, x[lo] - x[i], x[hi - 1] - x[i])), 2.0 * float(a2)


def _prepare(imu_t_ns, gyro, accel, fix_t_ns, fix_p, fix_sigma, options):
    imu_t_ns = np.asarray(imu_t_ns, dtype=np.int64)
    fix_t_ns = np.asarray(fix_t_ns, dtype=np.int64)
    fix_sigma = np.broadcast_to(np.asarray(fix_sigma, float), (len(fix_t_ns), 3))
    if len(fix_t_ns) < 10 * options.min_windows:
        raise GpsCalibrationError(f"only {len(fix_t_ns)} position fixes: {MOTION_ADVICE}")
    spans = select_windows(imu_t_ns, accel, fix_t_ns, options)
    return [_window(imu_t_ns, gyro, accel, fix_t_ns, np.asarray(fix_p, float), fix_sigma, s, options) for s in spans]


def scan_latency(
    imu_t_ns: np.ndarray, gyro: np.ndarray, accel: np.ndarray,
    fix_t_ns: np.ndarray, fix_p: np.ndarray, fix_sigma: np.ndarray,
    gravity: float, lever_arm_b: np.ndarray, options: GpsCalibOptions = GpsCalibOptions(),
    gyro_bias_prior: np.ndarray | None = None,
) -> LatencyScan:
    """Scan the fixes' time offset (IMU in body FRD, fixes in local NED with σ (N, 3) or (3,)).

    ``gyro_bias_prior`` (σ ``options.sigma_gyro_bias``), e.g. from a static stretch of the same
    record, keeps the short windows from trading gyro bias against attitude.
    """
    o = options
    windows = _prepare(imu_t_ns, gyro, accel, fix_t_ns, fix_p, fix_sigma, o)
    lever = np.asarray(lever_arm_b, dtype=float)
    fitter = _Fitter(gravity, o, gyro_bias_prior)
    n_side = int(round(o.max_offset_s / o.step_s))
    offsets = o.centre_s + o.step_s * np.arange(-n_side, n_side + 1)
    costs = np.zeros((len(offsets), len(windows)))
    start = [fitter.initial_state(w, lever, o.centre_s) for w in windows]
    # Outward from the centre, each candidate warm-started from its neighbour's fit.
    for direction in (range(n_side, len(offsets)), range(n_side - 1, -1, -1)):
        states = list(start)
        for i in direction:
            for k, w in enumerate(windows):
                fitted, _, window_cost, _, _ = fitter.fit([w], [states[k]], lever, offsets[i])
                states[k], costs[i, k] = fitted[0], window_cost[0]
    total = costs.sum(axis=1)
    i_min = int(np.argmin(total))
    if i_min in (0, len(offsets) - 1):
        raise GpsCalibrationError(
            f"the residual is smallest at the edge of the scan ({offsets[i_min] * 1e3:+.0f} ms): the offset may lie "
            f"beyond ±{o.max_offset_s * 1e3:.0f} ms around {o.centre_s * 1e3:+.0f} ms; widen the scan, or, if the "
            f"curve is flat, {MOTION_ADVICE}")
    offset, curvature = _parabola_min(offsets, total, i_min)
    n_fixes = sum(len(w.fix_t_ns) for w in windows)
    dof = max(3 * n_fixes - 15 * len(windows), 1)
    scale = max(1.0, float(total[i_min]) / dof)
    sigma = math.sqrt(2.0 * scale / curvature) if curvature > 0.0 else math.inf
    if sigma > o.max_sigma_offset_s:
        raise GpsCalibrationError(
            f"the time offset is not sharp: its residual curve gives ±{sigma * 1e3:.0f} ms (limit "
            f"{o.max_sigma_offset_s * 1e3:.0f} ms): too little motion; {MOTION_ADVICE}")
    per_window = np.array([_parabola_min(offsets, costs[:, k], int(np.argmin(costs[:, k])))[0] for k in range(len(windows))])
    return LatencyScan(
        offsets_s=offsets,
        cost=total,
        window_cost=costs,
        offset_s=offset,
        sigma_s=sigma,
        window_offsets_s=per_window,
        residual_ratio=math.sqrt(float(total[i_min]) / (3 * n_fixes)),
        windows=[(int(w.fix_t_ns[0]), int(w.fix_t_ns[-1])) for w in windows],
        n_fixes=n_fixes,
    )


def fit_lever_arm(
    imu_t_ns: np.ndarray, gyro: np.ndarray, accel: np.ndarray,
    fix_t_ns: np.ndarray, fix_p: np.ndarray, fix_sigma: np.ndarray,
    gravity: float, offset_s: float = 0.0, initial_lever_b: np.ndarray | None = None,
    options: GpsCalibOptions = GpsCalibOptions(), gyro_bias_prior: np.ndarray | None = None,
) -> LeverArmFit:
    """The antenna lever arm (body FRD) fitted over all windows at the fixes' time ``offset_s``."""
    o = replace(options, centre_s=offset_s, max_offset_s=0.0)
    windows = _prepare(imu_t_ns, gyro, accel, fix_t_ns, fix_p, fix_sigma, o)
    lever = np.zeros(3) if initial_lever_b is None else np.asarray(initial_lever_b, dtype=float)
    fitter = _Fitter(gravity, o, gyro_bias_prior)
    states = [fitter.initial_state(w, lever, offset_s) for w in windows]
    states, lever, fix_costs, J, _ = fitter.fit(windows, states, lever, offset_s, free_lever=True)
    n_fixes = sum(len(w.fix_t_ns) for w in windows)
    ratio = math.sqrt(sum(fix_costs) / (3 * n_fixes))
    try:
        cov = np.linalg.inv(J.T @ J)
    except np.linalg.LinAlgError:
        raise GpsCalibrationError(f"the lever arm is not observable: {ROTATION_ADVICE}") from None
    sigma = np.sqrt(np.maximum(np.diag(cov)[LEVER_ARM], 0.0)) * max(1.0, ratio)
    if np.max(sigma) > o.max_sigma_lever_m:
        raise GpsCalibrationError(
            f"the lever arm is not determined: ±{np.round(sigma, 3).tolist()} m (limit {o.max_sigma_lever_m:g} m): "
            f"{ROTATION_ADVICE}")
    return LeverArmFit(lever, sigma, offset_s, ratio, [(int(w.fix_t_ns[0]), int(w.fix_t_ns[-1])) for w in windows], n_fixes)
