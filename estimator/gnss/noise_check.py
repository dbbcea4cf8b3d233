"""A GPS's stated accuracy checked against what its fixes do: the noise it really has, when it lies.

A receiver reports a sigma with every fix (NMEA GST, MAVLink eph/epv, a dataset column). A wrong
one — a GST the receiver gets wrong, a driver that reads the wrong field, 1e-300 m — makes every
fix look like an outlier: the gate refuses them all, the filter resets to the next one with the
same impossible sigma, and does so for the rest of the flight.

The check measures the scatter itself. Between two fixes the filter knows how the antenna moved
(the IMU's prediction), so each fix minus the previous one's posterior residual,
``d_k = ν_k − r⁺_{k−1}``, is the difference of two fixes' errors: per axis its variance is twice the
fix noise, whatever the filter's own error (shared by both, it cancels) and whatever offset a
jump adds for many fixes in a row (it also cancels, except at its two edges). Over a window of
them, the lowest tenth of their sizes decides whether a claim is believed (it ignores those edges,
and the half of the differences that multipath on a third of the fixes spoils: those fixes are
the gate's to refuse); their median gives the weight.

When the claimed sigma is far below that scatter *and* most of the latest fixes are refused under
their claims (NIS out of band), the claim is not believed: fixes are weighed with the measured
sigma (never below the claimed one, never above ``max_sigma_m``) until the claims are consistent
again. A claim below a tenth of the scatter is not believed at once, without waiting for the
NIS: a single such fix that happened to pass the gate would collapse the position covariance. A reset because every fix was refused is that NIS out of band, for seconds:
when the scatter says the claim is the problem, the reset re-initialises from the fix weighed
with the noise measured. After two such resets in a row it takes what it has measured so far
(``min_pairs_after_resets``) rather than wait for more: a reset that re-initialises from the same
claim would only repeat. Pure computation: no I/O, no clocks.
"""

from __future__ import annotations

import math
from bisect import bisect_left, insort
from collections import deque
from typing import Callable
from dataclasses import dataclass

import numpy as np

from vtolpose.estimator.core.kalman import chi2_gate
from vtolpose.estimator.core.measurements import GpsFix
from vtolpose.estimator.core.state import FilterState
from vtolpose.estimator.gnss.gps_update import GPS_COLS, GpsModel, gps_sigmas

MAD_TO_SIGMA = 1.4826  # a normal variable's sigma from its median absolute deviation
LOWER_DECILE_ABS = 0.1257  # the 10th percentile of |x| for a standard normal x


def median_of_sorted(values: list[float]) -> float:
    """``np.median`` of ``values`` (none negative, none NaN: :class:`SortedSizes` counts those apart) given
    sorted, with its arithmetic (the middle two summed, then halved): on a window of a hundred floats, every
    fix, numpy's call costs ten times the sort."""
    n = len(values)
    if n % 2:
        return values[n // 2]
    return (values[n // 2 - 1] + values[n // 2]) / 2


def percentile_of_sorted(values: list[float], q: float) -> float:
    """``np.percentile(values, 100 q)`` (its default, linear interpolation between the order statistics around
    ``(n − 1) q``, with its arithmetic) of ``values`` (none negative, none NaN) given sorted."""
    n = len(values)
    virtual = (n - 1) * q
    below = n - 1 if virtual >= n - 1 else math.floor(virtual)
    above = n - 1 if virtual >= n - 1 else below + 1
    gamma = virtual - below
    a, b = values[below], values[above]
    return b - (b - a) * (1 - gamma) if gamma >= 0.5 else a + (b - a) * gamma


class SortedSizes:
    """Sizes (never negative) kept in order as they come and go: a window's median and percentiles without a
    sort per fix. NaN is counted apart (it has no place in the order; any makes every statistic NaN)."""

    def __init__(self) -> None:
        self._values: list[float] = []
        self._nans = 0

    def add(self, size: float) -> None:
        if size != size:
            self._nans += 1
        else:
            insort(self._values, size)

    def remove(self, size: float) -> None:
        if size != size:
            self._nans -= 1
        else:
            del self._values[bisect_left(self._values, size)]

    def median(self) -> float:
        """``np.median`` of the sizes (NaN if any is, as numpy's)."""
        return math.nan if self._nans else median_of_sorted(self._values)

    def percentile(self, q: float) -> float:
        """``np.percentile`` of the sizes at ``100 q`` (NaN if any is)."""
        return math.nan if self._nans else percentile_of_sorted(self._values, q)


@dataclass(frozen=True, slots=True)
class NoiseCheckOptions:
    enabled: bool = True
    window: int = 100  # successive fix pairs the scatter is measured over (10 s at 10 Hz) ...
    nis_window: int = 20  # ... and fixes the NIS under their claims is judged over (the latest claims)
    min_pairs: int = 10  # a verdict needs at least this many (after two resets in a row: min_pairs_after_resets)
    min_pairs_after_resets: int = 3
    distrust_ratio: float = 3.0  # measured sigma beyond this many times the claimed one: not believed ...
    trust_ratio: float = 2.0  # ... believed again below this many times
    implausible_ratio: float = 10.0  # a single fix claiming less than the scatter over this: weighed with the scatter
    min_sigma_m: float = 0.1  # differences this small are the IMU's prediction between fixes, not the GPS
    max_sigma_m: float = 50.0  # the largest noise the check will ever assign
    max_pair_gap_s: float = 2.0  # fixes further apart than this are no pair (the motion between them is not known well)
    nis_probability: float = 0.999  # the window's lower-quartile NIS beyond this χ² quantile (3 dof): out of band

    def __post_init__(self) -> None:
        if not (2 <= self.min_pairs_after_resets <= self.min_pairs <= self.window and 1 <= self.nis_window):
            raise ValueError("gps noise check: need 2 <= min_pairs_after_resets <= min_pairs <= window, nis_window >= 1")
        if not (1.0 < self.trust_ratio <= self.distrust_ratio <= self.implausible_ratio):
            raise ValueError("gps noise check: need 1 < trust_ratio <= distrust_ratio <= implausible_ratio")
        if not (0.0 < self.min_sigma_m < self.max_sigma_m) or not (0.0 < self.nis_probability < 1.0):
            raise ValueError("gps noise check: need 0 < min_sigma_m < max_sigma_m and nis_probability in (0, 1)")


@dataclass(frozen=True, slots=True)
class NoiseVerdict:
    """What the check believes now: None while the claims are believed."""

    sigma_h_m: float
    sigma_v_m: float
    claimed_h_m: float
    since_t_ns: int

    def describe(self) -> str:
        return f"GPS claims {self.claimed_h_m:.3f} m, behaves like {self.sigma_h_m:.1f} m"


class GpsNoiseCheck:
    """See the module docstring. The filter calls :meth:`believed` on each fix, :meth:`before_update` with
    the state before its update and :meth:`after_update` with the state after it (and after any reset)."""

    def __init__(self, options: NoiseCheckOptions | None = None, sigma_floor_m: float = 1e-3,
                 on_change: Callable[[int, str], None] | None = None) -> None:
        self.options = options or NoiseCheckOptions()
        self.sigma_floor_m = sigma_floor_m
        self.verdict: NoiseVerdict | None = None
        self.adjusted = 0  # fixes weighed with the measured sigma
        self.changes = 0  # times the belief changed (either way)
        self.on_change = on_change  # told (t_ns, text) of each change of belief: the filter makes it an event
        n = self.options.window
        self._diffs: deque[tuple[float, float, float]] = deque(maxlen=n)  # d_k, NED
        # Their components' sizes, in order: horizontal (north and east alike) and vertical.
        self._horizontal, self._vertical = SortedSizes(), SortedSizes()
        m = self.options.nis_window
        self._before_start: deque[GpsFix] = deque(maxlen=max(self.options.min_pairs, m))  # heard before the start
        self._nis: deque[float] = deque(maxlen=m)  # under the claimed noise ...
        self._nis_sizes = SortedSizes()  # ... and the same in order
        self._claimed_h: deque[float] = deque(maxlen=m)
        self._claimed_v: deque[float] = deque(maxlen=m)
        self._pending: tuple[int, np.ndarray, float, float] | None = None  # this fix: t, innovation, claimed σh, σv
        self._last_posterior: tuple[int, list[float]] | None = None  # the previous fix: t, posterior residual
        self._resets_in_a_row = 0
        self._scatter = (0.0, 0.0, 0.0)  # the fixes' scatter (robust horizontal; horizontal, vertical), once judged
        self._said_h = math.nan  # the latest fix's own sigma_h, before the filter's floor

    # ------------------------------------------------------------------------------- filter hooks
    def believed(self, fix: GpsFix) -> GpsFix:
        """``fix`` with the sigmas the filter should weigh it with (the fix itself while claims are believed)."""
        if not self.options.enabled:
            return fix
        v = self.verdict
        claimed_h, claimed_v = self._claimed(fix)
        if v is not None:
            floor_h, floor_v = v.sigma_h_m, v.sigma_v_m
        elif claimed_h * self.options.implausible_ratio < self._scatter[0]:
            # Before the verdict, one fix claiming a tenth of what the fixes have shown is not believed either: one
            # such fix that happens to pass the gate would collapse the position covariance meanwhile.
            floor_h, floor_v = self._scatter[1:]
        else:
            return fix
        if claimed_h >= floor_h and claimed_v >= floor_v:
            return fix
        self.adjusted += 1
        return GpsFix(fix.t_ns, fix.p_ned, max(claimed_h, floor_h), max(claimed_v, floor_v))

    def before_update(self, state: FilterState, fix: GpsFix, model: GpsModel) -> None:
        """The fix's innovation against the state before its update; ``fix`` as received."""
        if not self.options.enabled:
            return
        claimed_h, claimed_v = self._claimed(fix)
        arm = model.arm(state)
        H = model.jacobian(state, arm)
        hph = H @ state.cov[GPS_COLS, GPS_COLS] @ H.T
        nu = np.asarray(fix.p_ned, dtype=float) - model.predict(state, arm)
        s = hph + np.diag([claimed_h**2, claimed_h**2, claimed_v**2])
        try:
            nis = float(nu @ np.linalg.solve(s, nu))
        except np.linalg.LinAlgError:
            nis = math.inf
        self.innovation(fix, nu, nis)

    def claims(self, fix: GpsFix) -> tuple[float, float] | None:
        """The sigmas :meth:`before_update` weighs ``fix``'s innovation with; None while the check is off."""
        return self._claimed(fix) if self.options.enabled else None

    def innovation(self, fix: GpsFix, nu: np.ndarray, nis: float) -> None:
        """:meth:`before_update` given the fix's innovation ``nu`` and its NIS under :meth:`claims` (the filter's
        compiled fix works both out with its update)."""
        if not self.options.enabled:
            return
        claimed_h, claimed_v = self._claimed(fix)
        self._pending = (fix.t_ns, nu, claimed_h, claimed_v)
        self._said_h = float(fix.sigma_h)  # the claim as the receiver made it, for the operator
        last = self._last_posterior
        if last is not None and 0 < fix.t_ns - last[0] <= self.options.max_pair_gap_s * 1e9:
            (north, east, down), (pn, pe, pd) = nu.tolist(), last[1]
            if not (math.isfinite(north) and math.isfinite(east) and math.isfinite(down)):
                return
            self._take_diff((north - pn, east - pe, down - pd))
            nis = nis if math.isfinite(nis) else 1e300
            if len(self._nis) == self._nis.maxlen:
                self._nis_sizes.remove(self._nis[0])
            self._nis.append(nis)
            self._nis_sizes.add(nis)
            self._claimed_h.append(claimed_h)
            self._claimed_v.append(claimed_v)

    def after_update(self, t_ns: int, posterior_residual: np.ndarray, accepted: bool) -> None:
        """The fix's residual against the state after its update (or reset); re-judges the claims."""
        if not self.options.enabled or self._pending is None or self._pending[0] != t_ns:
            return
        self._pending = None
        self._last_posterior = (t_ns, np.asarray(posterior_residual, dtype=float).tolist())
        if accepted:
            self._resets_in_a_row = 0
        self._judge(t_ns)

    def on_reset(self, fix: GpsFix) -> GpsFix:
        """The filter resets to ``fix`` (as received) because every fix was refused: the fix to re-initialise
        from. From the second such reset in a row, what has been measured so far is believed."""
        if not self.options.enabled:
            return fix
        self._resets_in_a_row += 1
        self._judge(fix.t_ns)
        return self.believed(fix)

    def before_start(self, fix: GpsFix) -> bool:
        """A fix heard before the filter has a state to predict it: the last fixes (``nis_window``, at least
        ``min_pairs``) are fitted with a constant acceleration in time, and the fit's scatter judged against
        their claims. True when
        the belief has just changed (the caller re-weighs the fixes it holds)."""
        if not self.options.enabled:
            return False
        self._before_start.append(fix)
        fixes = list(self._before_start)
        if len(fixes) < self.options.min_pairs or self.verdict is not None:
            return False
        t = np.array([(f.t_ns - fixes[-1].t_ns) * 1e-9 for f in fixes])
        if np.ptp(t) <= 0.0:
            return False
        y = np.array([np.asarray(f.p_ned, dtype=float) for f in fixes])
        a = np.column_stack([np.ones_like(t), t, t * t])
        residual = y - a @ np.linalg.lstsq(a, y, rcond=None)[0]
        dof = len(fixes) - 3
        sigma_h = math.sqrt(float(np.sum(residual[:, :2] ** 2)) / (2 * dof))
        sigma_v = math.sqrt(float(np.sum(residual[:, 2] ** 2)) / dof)
        claimed = np.array([self._claimed(f) for f in fixes])
        claimed_h, claimed_v = float(np.median(claimed[:, 0])), float(np.median(claimed[:, 1]))
        if sigma_h > max(self.options.distrust_ratio * claimed_h, self.options.min_sigma_m):
            hi = self.options.max_sigma_m
            said = float(np.median([f.sigma_h for f in fixes]))
            self.verdict = NoiseVerdict(min(sigma_h, hi), min(max(sigma_v, claimed_v), hi), said, fix.t_ns)
            self._changed(fix.t_ns, f"{self.verdict.describe()} (before the start): its fixes weighed as {sigma_h:.1f} m")
            return True
        return False

    # ------------------------------------------------------------------------------- the verdict
    def measured_sigmas(self) -> tuple[float, float] | None:
        """The fixes' own noise (horizontal, vertical) from the window's differences, bounded; None: too few."""
        if len(self._diffs) < self.options.min_pairs_after_resets:
            return None
        # Each difference carries two fixes' errors: per axis variance 2σ². (The innovations' own size is no
        # measure of it: a jump of 20 m held for seconds would pass for noise and be followed.) Errors that are
        # correlated from fix to fix cancel in part: for them this is a lower bound.
        h = MAD_TO_SIGMA * self._horizontal.median() / math.sqrt(2.0)
        v = MAD_TO_SIGMA * self._vertical.median() / math.sqrt(2.0)
        lo, hi = self.sigma_floor_m, self.options.max_sigma_m
        return min(max(h, lo), hi), min(max(v, lo), hi)

    def robust_sigma_h(self) -> float:
        """The horizontal scatter from the lowest tenth of the differences' sizes: what decides whether a claim
        is believed. Multipath on a third of the fixes spoils half the differences and lifts their median (the
        weight's measure) above three claimed sigmas; those fixes are the gate's to refuse, not a lie."""
        return self._horizontal.percentile(10 / 100) / (LOWER_DECILE_ABS * math.sqrt(2.0))

    def _take_diff(self, diff: tuple[float, float, float]) -> None:
        """A new difference into the window (the oldest leaves it once it is full), its sizes into their orders."""
        diffs = self._diffs
        if len(diffs) == diffs.maxlen:
            north, east, down = diffs[0]
            self._horizontal.remove(abs(north))
            self._horizontal.remove(abs(east))
            self._vertical.remove(abs(down))
        diffs.append(diff)
        north, east, down = diff
        self._horizontal.add(abs(north))
        self._horizontal.add(abs(east))
        self._vertical.add(abs(down))

    def _judge(self, t_ns: int) -> None:
        opts = self.options
        needed = opts.min_pairs_after_resets if self._resets_in_a_row >= 2 else opts.min_pairs
        measured = self.measured_sigmas() if len(self._diffs) >= needed else None
        if measured is None:
            return
        sigma_h, sigma_v = measured
        robust_h = self.robust_sigma_h()
        if len(self._diffs) >= opts.min_pairs:
            self._scatter = (robust_h, sigma_h, sigma_v)
        claimed_h, claimed_v = self._claimed_h[-1], self._claimed_v[-1]  # what the latest fix claims
        # A reset for refused fixes is itself the NIS out of band, for gps_reset_after_s on end.
        # Most of the latest fixes refused under their claims (the lower quartile of their NIS beyond the gate):
        # a third of them off by multipath is not that.
        nis_out = self._resets_in_a_row > 0 or self._nis_sizes.percentile(25 / 100) > chi2_gate(3, opts.nis_probability)
        if self.verdict is None:
            implausible = robust_h > max(opts.implausible_ratio * claimed_h, opts.min_sigma_m)  # no NIS needed
            if implausible or (nis_out and robust_h > max(opts.distrust_ratio * claimed_h, opts.min_sigma_m)):
                self.verdict = NoiseVerdict(sigma_h, max(sigma_v, claimed_v), self._said_h, t_ns)
                self._changed(t_ns, f"{self.verdict.describe()}: its fixes weighed as {sigma_h:.1f} m")
        elif robust_h < max(opts.trust_ratio * claimed_h, opts.min_sigma_m) and not nis_out:
            old, self.verdict = self.verdict, None
            self._changed(t_ns, f"GPS claims {self._said_h:.3f} m again consistent with its fixes (was weighed as "
                                f"{old.sigma_h_m:.1f} m)")
        else:
            old = self.verdict
            if len(self._diffs) < opts.window // 2:  # a few pairs may say less than the fit or the reset said: keep that
                sigma_h, sigma_v = max(sigma_h, old.sigma_h_m), max(sigma_v, old.sigma_v_m)
            self.verdict = NoiseVerdict(max(sigma_h, claimed_h), max(sigma_v, claimed_v), self._said_h, old.since_t_ns)

    def _changed(self, t_ns: int, text: str) -> None:
        self.changes += 1
        if self.on_change is not None:
            self.on_change(t_ns, text)

    def _claimed(self, fix: GpsFix) -> tuple[float, float]:
        """The fix's own sigmas with the filter's floor and the σ_v = √2 σ_h fallback (as the update uses them)."""
        return gps_sigmas(fix, self.sigma_floor_m)

    def report(self) -> dict:
        """For the status document and the replay report."""
        v = self.verdict
        return {
            "believed": v is None,
            "claimed_sigma_h_m": None if v is None else round(v.claimed_h_m, 6),
            "measured_sigma_h_m": None if v is None else round(v.sigma_h_m, 3),
            "measured_sigma_v_m": None if v is None else round(v.sigma_v_m, 3),
            "text": None if v is None else v.describe(),
            "fixes_adjusted": self.adjusted,
            "changes": self.changes,
        }
