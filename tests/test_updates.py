"""GPS measurement model and the shared EKF update."""

import numpy as np
import pytest

from vtolpose.estimator.gnss.gps_update import GpsModel, GpsUpdater, gps_sigmas
from vtolpose.estimator.core.kalman import chi2_gate, ekf_update
from vtolpose.estimator.core.measurements import GpsFix
from vtolpose.estimator.core.rotation import quat_exp, quat_from_euler, quat_mul
from vtolpose.estimator.core.state import FilterState, StateLayout


def make_state(variant="biases", n_landmarks=0, seed=0):
    rng = np.random.default_rng(seed)
    s = FilterState(StateLayout(variant))
    s.p = rng.normal(size=3)
    s.v = rng.normal(size=3)
    s.q = quat_from_euler(0.2, -0.1, 0.7)
    s.landmarks = rng.normal(size=(n_landmarks, 6))
    n = s.robot_dim + 6 * n_landmarks
    A = rng.normal(size=(n, n)) * 0.1
    s.cov = A @ A.T + 0.01 * np.eye(n)
    return s


def test_gps_jacobian_matches_central_differences():
    model = GpsModel(np.array([0.3, -0.2, -0.5]))
    s = make_state()
    H = model.jacobian(s)
    h = 1e-6
    numeric = np.zeros((3, 9))
    for i in range(9):
        for sign in (1, -1):
            t = s.copy()
            d = np.zeros(9)
            d[i] = sign * h
            t.p = t.p + d[0:3]
            t.v = t.v + d[3:6]
            t.q = quat_mul(quat_exp(d[6:9]), t.q)
            numeric[:, i] += sign * model.predict(t) / (2 * h)
    assert np.allclose(H, numeric, atol=1e-8)


def test_chi2_gate_values():
    assert chi2_gate(3) == pytest.approx(7.81, abs=0.01)
    assert chi2_gate(2) == pytest.approx(5.99, abs=0.01)


def test_vertical_sigma_defaults_to_sqrt2_horizontal():
    fix = GpsFix(0, np.zeros(3), 0.02, float("nan"))
    assert gps_sigmas(fix, 1e-3) == pytest.approx((0.02, 0.02 * np.sqrt(2)))


def test_update_moves_toward_measurement_and_shrinks_covariance():
    s = make_state(n_landmarks=2)
    upd = GpsUpdater(np.zeros(3), gate=None)
    target = s.p + np.array([0.1, -0.1, 0.05])
    trace_before = np.trace(s.cov)
    out = upd.update(s, GpsFix(0, target, 0.01, 0.014))
    assert out.accepted
    assert np.linalg.norm(s.p - target) < 0.02
    assert np.trace(s.cov) < trace_before
    assert np.allclose(s.cov, s.cov.T)
    assert np.all(np.linalg.eigvalsh(s.cov) > 0)


def test_update_equals_textbook_kalman_on_linear_model():
    s = make_state("thesis")
    P0, x0 = s.cov.copy(), s.p.copy()
    H = np.zeros((3, 9))
    H[:, :3] = np.eye(3)
    R = np.diag([0.04, 0.04, 0.08])
    z = x0 + np.array([0.2, 0.1, -0.3])
    K = P0 @ H.T @ np.linalg.inv(H @ P0 @ H.T + R)
    ekf_update(s, slice(0, 9), H, z - x0, R)
    assert np.allclose(s.p, x0 + (K @ (z - x0))[:3])
    assert np.allclose(s.cov, (np.eye(9) - K @ H) @ P0, atol=1e-12)


def test_outlier_rejected_and_state_untouched():
    s = make_state()
    s.cov[:3, :3] = np.eye(3) * 1e-4
    before = s.copy()
    out = GpsUpdater(np.zeros(3), gate=chi2_gate(3)).update(s, GpsFix(0, s.p + [20.0, 0, 0], 0.02, 0.03))
    assert not out.accepted and out.reason == "chi2 gate" and out.nis > 1e5
    assert np.array_equal(s.p, before.p) and np.array_equal(s.cov, before.cov)


def test_singular_innovation_covariance_is_reported_not_raised():
    s = make_state()
    s.cov[:] = 0.0
    out = ekf_update(s, slice(0, 3), np.eye(3), np.ones(3), np.zeros((3, 3)))
    assert not out.accepted and "singular" in out.reason
    assert np.all(np.isfinite(s.cov))


def test_held_states_keep_value_and_covariance():
    s = make_state(n_landmarks=1)
    held = np.zeros(s.dim, dtype=bool)
    held[6:] = True
    before = s.copy()
    ekf_update(s, slice(0, 9), GpsModel(np.array([0.5, 0, 0])).jacobian(s), np.array([0.3, 0.2, 0.1]), np.eye(3) * 0.01, held=held)
    assert np.allclose(s.q, before.q) and np.allclose(s.landmarks, before.landmarks)
    assert np.allclose(s.cov[6:, 6:], before.cov[6:, 6:])
    assert not np.allclose(s.p, before.p)
    assert np.all(np.linalg.eigvalsh(s.cov) > 0)


@pytest.mark.parametrize("pattern", ["gps, heading unknown", "camera, one landmark's depth held"])
def test_a_held_state_is_never_corrected_and_its_covariance_follows_the_schmidt_form(pattern):
    """Against the Schmidt–Kalman update written out densely: the gain ``K`` with the held rows zeroed,
    ``P+ = (I - K H) P (I - K H)ᵀ + K R Kᵀ`` (Joseph form, valid for any gain). Held values stay
    exactly as they were; the other states move by ``K ε``; every cross-covariance follows."""
    s = make_state("biases", n_landmarks=2, seed=5)
    n = s.dim
    rng = np.random.default_rng(11)
    held = np.zeros(n, dtype=bool)
    if pattern.startswith("gps"):
        cols = np.arange(9)
        H_cols = GpsModel(np.array([0.1, -0.2, -0.3])).jacobian(s)
        held[6:] = True  # attitude, biases and map wait for a heading (the estimator's mask)
    else:
        lm = s.robot_dim + 6  # the second landmark's six columns
        cols = np.concatenate([np.arange(0, 3), np.arange(6, 9), np.arange(lm, lm + 6)])
        H_cols = rng.normal(size=(4, len(cols)))
        held[lm + 5] = True  # its inverse depth: no baseline yet
    m = H_cols.shape[0]
    residual, R = rng.normal(size=m) * 0.1, np.diag(rng.uniform(0.01, 0.05, size=m))
    H = np.zeros((m, n))
    H[:, cols] = H_cols
    P = s.cov.copy()
    K = P @ H.T @ np.linalg.inv(H @ P @ H.T + R)
    K[held] = 0.0
    I_KH = np.eye(n) - K @ H
    expected_cov = I_KH @ P @ I_KH.T + K @ R @ K.T
    before = s.copy()
    assert ekf_update(s, cols, H_cols, residual, R, held=held).accepted
    dx = K @ residual
    assert np.allclose(s.cov, expected_cov, rtol=1e-9, atol=1e-12)
    assert np.array_equal(s.cov[np.ix_(held, held)], before.cov[np.ix_(held, held)])
    assert np.allclose(s.p, before.p + dx[0:3], atol=1e-12) and np.allclose(s.v, before.v + dx[3:6], atol=1e-12)
    assert not np.allclose(s.cov[np.ix_(~held, held)], before.cov[np.ix_(~held, held)])  # cross-terms do move
    if pattern.startswith("gps"):
        assert np.allclose(s.q, before.q, rtol=0, atol=1e-15)
        assert np.array_equal(s.b_g, before.b_g) and np.array_equal(s.b_a, before.b_a)
        assert np.array_equal(s.landmarks, before.landmarks)
    else:
        assert s.landmarks[1, 5] == before.landmarks[1, 5]
        assert np.allclose(s.landmarks.reshape(-1), before.landmarks.reshape(-1) + dx[s.robot_dim:], atol=1e-12)


@pytest.mark.parametrize("m", [1, 2, 3, 4])
def test_small_and_stacked_updates_equal_the_textbook_gain_and_nis(m):
    """m ≤ 3 goes through the scalar Cholesky, larger m through LAPACK: both are the textbook update."""
    rng = np.random.default_rng(m)
    s = make_state("biases")
    A = rng.normal(size=(15, 15))
    s.cov = A @ A.T * 1e-3 + np.eye(15) * 1e-4
    P0, x0 = s.cov.copy(), np.concatenate([s.p, s.v])
    H = rng.normal(size=(m, 15))
    R = np.diag(rng.uniform(1e-3, 1e-2, m))
    r = rng.normal(size=m) * 0.01
    S = H @ P0 @ H.T + R
    K = P0 @ H.T @ np.linalg.inv(S)
    out = ekf_update(s, slice(0, 15), H, r, R)
    assert out.accepted and out.nis == pytest.approx(float(r @ np.linalg.solve(S, r)), rel=1e-9)
    np.testing.assert_allclose(np.concatenate([s.p, s.v]), x0 + (K @ r)[:6], rtol=0, atol=1e-12)
    np.testing.assert_allclose(s.cov, (np.eye(15) - K @ H) @ P0, rtol=0, atol=1e-12)


def test_small_inverse_refuses_what_is_not_positive_definite():
    from vtolpose.estimator.core.update_kernel import small_inverse
    for S in (np.array([[0.0]]), np.array([[np.nan]]), np.array([[1.0, 2.0], [2.0, 1.0]]),
              np.diag([1.0, 1.0, -1e-9]), np.diag([1.0, np.inf, 1.0])):
        assert not small_inverse(S)[0]
    S = np.array([[4.0, 1.0, 0.5], [1.0, 3.0, 0.2], [0.5, 0.2, 2.0]])
    positive, S_inv, L_inv = small_inverse(S)
    assert positive
    np.testing.assert_allclose(S_inv, np.linalg.inv(S), rtol=1e-12)
    np.testing.assert_allclose(L_inv, np.linalg.inv(np.linalg.cholesky(S)), rtol=1e-12, atol=1e-15)


@pytest.mark.parametrize("m", [1, 2, 3])
@pytest.mark.parametrize("case", ["plain", "held", "gated", "singular", "non_finite"])
def test_the_compiled_small_update_is_bit_for_bit_the_numpy_one(m, case):
    """One to three rows on a column range run compiled (numba); the numpy path is the reference: the same
    state, covariance, NIS and outcome, to the last bit, whatever the outcome."""
    from vtolpose.estimator.core.kalman import _compiled_update, _numpy_update

    rng = np.random.default_rng(10 * m + len(case))
    start = make_state("biases")
    A = rng.normal(size=(15, 15))
    start.cov = A @ A.T * 1e-3 + np.eye(15) * 1e-4
    cols = slice(3, 12)
    H = rng.normal(size=(m, 9))
    R = np.diag(rng.uniform(1e-3, 1e-2, m))
    r = rng.normal(size=m) * 0.01
    gate, held = 1e6, None
    if case == "held":
        held = rng.random(15) < 0.4
    elif case == "gated":
        gate = 1e-12
    elif case == "singular":
        R = -np.eye(m) * 10.0
    elif case == "non_finite":
        r[-1] = np.nan
    outcomes = []
    for update in (_compiled_update, _numpy_update):
        s = start.copy()
        out = update(s, cols, H, r, R, gate, held)
        outcomes.append((out.accepted, out.reason, out.dof, s))
        if case in ("plain", "held"):
            assert out.accepted
    (acc_c, why_c, dof_c, s_c), (acc_n, why_n, dof_n, s_n) = outcomes
    assert (acc_c, why_c, dof_c) == (acc_n, why_n, dof_n)
    for name in ("p", "v", "q", "b_g", "b_a", "cov"):
        assert np.array_equal(getattr(s_c, name), getattr(s_n, name)), name
    nis = [_compiled_update(start.copy(), cols, H, r, R, gate, held).nis, _numpy_update(start.copy(), cols, H, r, R, gate, held).nis]
    assert nis[0] == nis[1] or (np.isnan(nis[0]) and np.isnan(nis[1]))


@pytest.mark.parametrize("case", ["plain", "landmarks", "held", "gated", "singular", "non_finite", "no_gate"])
def test_the_compiled_gps_update_is_bit_for_bit_the_model_and_numpy_one(case):
    """A fix's update runs as one compiled call (gps_kernel: lever arm, residual, Jacobian, noise, update);
    the model's prediction and Jacobian through the numpy update are the reference: the same state,
    covariance, NIS and outcome, to the last bit, for any attitude, lever arm and outcome."""
    from vtolpose.estimator.core.kalman import _numpy_update
    from vtolpose.estimator.gnss.gps_update import GPS_COLS

    rng = np.random.default_rng(len(case))
    for trial in range(20):
        start = make_state("biases", n_landmarks=2 if case == "landmarks" else 0, seed=trial)
        start.q = quat_exp(rng.normal(size=3) * 2.0)
        lever = rng.normal(size=3) * 0.5
        fix = GpsFix(1, start.p + rng.normal(size=3) * 0.3, float(rng.uniform(0.05, 2.0)),
                     float(rng.uniform(0.05, 3.0)) if trial % 2 else float("nan"))
        gps = GpsUpdater(lever, gate=None if case == "no_gate" else chi2_gate(3, 0.999))
        held = None
        if case == "held":
            held = rng.random(start.dim) < 0.4
        elif case == "gated":
            gps.gate = 1e-9
        elif case == "singular":
            start.cov = -np.eye(start.dim) * 1e3
        elif case == "non_finite":
            fix = GpsFix(1, np.array([np.nan, 0.0, 0.0]), 1.0, 1.0)
        results = []
        for path in ("compiled", "model", "numpy"):
            s = start.copy()
            if path == "compiled":
                out = gps.update(s, fix, held)
            elif path == "model":
                out = gps.update_reference(s, fix, held)
            else:
                arm = gps.model.arm(s)
                residual = np.asarray(fix.p_ned, dtype=float) - gps.model.predict(s, arm)
                out = _numpy_update(s, GPS_COLS, gps.model.jacobian(s, arm), residual, gps.noise(fix), gps.gate, held)
            results.append((out, s))
        if case in ("plain", "landmarks", "held", "no_gate"):
            assert results[0][0].accepted
        else:
            assert not results[0][0].accepted
        (ref, ref_state), others = results[2], results[:2]
        for out, s in others:
            assert (out.accepted, out.reason, out.dof) == (ref.accepted, ref.reason, ref.dof)
            assert out.nis == ref.nis or (np.isnan(out.nis) and np.isnan(ref.nis))
            for name in ("p", "v", "q", "b_g", "b_a", "landmarks", "cov"):
                assert np.array_equal(getattr(s, name), getattr(ref_state, name)), (case, trial, name)


def test_a_gps_update_on_a_covariance_that_is_not_contiguous_takes_the_model_path():
    """The compiled call needs a C-ordered covariance; any other takes the model's path, with the same result."""
    start = make_state("biases")
    fix = GpsFix(1, start.p + 0.1, 0.5, 0.8)
    gps = GpsUpdater(np.array([0.1, -0.2, 0.3]), gate=None)
    a, b = start.copy(), start.copy()
    b.cov = np.asfortranarray(b.cov)
    assert not b.cov.flags.c_contiguous
    out_a, out_b = gps.update(a, fix), gps.update(b, fix)
    assert out_a.accepted and out_b.accepted and out_a.nis == out_b.nis
    assert np.array_equal(a.p, b.p) and np.array_equal(a.q, b.q) and np.array_equal(a.cov, b.cov)


@pytest.mark.parametrize("variant", ["biases", "thesis"])
@pytest.mark.parametrize("case", ["plain", "gated", "singular", "non_finite", "unchecked"])
def test_the_filters_compiled_fix_is_the_noise_checks_update_and_residual_in_python(variant, case):
    """Without a map the filter fuses a fix in one compiled call (gps_kernel.filter_fix): the noise check's
    innovation and NIS under the claimed sigmas, the update, the injection and the residual after it. The
    Python path (before_update, update_reference, FilterState.inject, residual) is the reference: the same
    state and outcome to the last bit, the same innovation, NIS and residual in the noise check."""
    from vtolpose.estimator.gnss.noise_check import GpsNoiseCheck

    rng = np.random.default_rng(len(case) + 10 * len(variant))
    for trial in range(20):
        start = make_state(variant, seed=trial)
        start.q = quat_exp(rng.normal(size=3) * 2.0)
        start.b_g, start.b_a = rng.normal(size=3) * 1e-3, rng.normal(size=3) * 1e-2
        lever = rng.normal(size=3) * 0.5
        raw = GpsFix(2, start.p + rng.normal(size=3) * 0.3, float(rng.uniform(0.05, 2.0)),
                     float(rng.uniform(0.05, 3.0)) if trial % 2 else float("nan"))
        weighed = GpsFix(raw.t_ns, raw.p_ned, raw.sigma_h * rng.uniform(1.0, 3.0), raw.sigma_v)  # the check's belief
        gps = GpsUpdater(lever, gate=1e6 if trial % 2 else None)
        if case == "gated":
            gps.gate = 1e-9
        elif case == "singular":
            start.cov = -np.eye(start.dim) * 1e3
        elif case == "non_finite":
            raw = weighed = GpsFix(2, np.array([np.nan, 0.0, 0.0]), 1.0, 1.0)
        checks, previous = [], rng.normal(size=3) * 0.1
        for _ in range(2):
            check = GpsNoiseCheck(sigma_floor_m=gps.sigma_floor_m)
            check.options = type(check.options)(enabled=case != "unchecked")
            check._last_posterior = (1, previous)  # a previous fix: this one's difference is taken
            checks.append(check)
        compiled, python = start.copy(), start.copy()
        out_c, info = gps.update_filter(compiled, weighed, checks[0].claims(raw))
        checks[0].innovation(raw, info[3:6], float(info[2]))
        checks[0].after_update(raw.t_ns, info[6:9], out_c.accepted)
        checks[1].before_update(python, raw, gps.model)
        out_p = gps.update_reference(python, weighed)
        checks[1].after_update(raw.t_ns, gps.residual(python, raw), out_p.accepted)
        assert out_c.accepted == (case in ("plain", "unchecked"))
        assert (out_c.accepted, out_c.reason, out_c.dof) == (out_p.accepted, out_p.reason, out_p.dof)
        assert out_c.nis == out_p.nis or (np.isnan(out_c.nis) and np.isnan(out_p.nis))
        for name in ("p", "v", "q", "b_g", "b_a", "cov"):
            assert np.array_equal(getattr(compiled, name), getattr(python, name)), (case, trial, name)
        np.testing.assert_array_equal(info[6:9], gps.residual(python, raw))
        assert list(checks[0]._diffs) == list(checks[1]._diffs)
        np.testing.assert_allclose(list(checks[0]._nis), list(checks[1]._nis), rtol=1e-12)
        assert len(checks[0]._nis) == (case not in ("non_finite", "unchecked"))


@pytest.mark.parametrize("kernel", ["compiled", "interpreted"])
def test_the_gauge_transfer_is_numpys_outer_products_to_the_bit(kernel):
    """``P ← T P Tᵀ`` with ``T = I + d e_ψᵀ`` in one compiled pass (or its plain-Python body, which a cold kernel cache
    runs) equals the three outer products it replaces, bit for bit; a covariance that is not C-ordered takes numpy's
    path to the same numbers."""
    from vtolpose.estimator.core import covariance, update_kernel

    rng = np.random.default_rng(5)
    n = 57
    A = rng.normal(size=(n, n))
    cov = A @ A.T * 1e-3
    before, after = rng.normal(size=n), rng.normal(size=n)
    d = after - before
    c = cov[:, covariance.YAW].copy()
    expected = cov + (np.outer(d, c) + np.outer(c, d) + cov[covariance.YAW, covariance.YAW] * np.outer(d, d))
    transfer = update_kernel.gauge_transfer if kernel == "compiled" else update_kernel.gauge_transfer.py_func
    got = cov.copy()
    transfer(got, d, covariance.YAW)
    np.testing.assert_array_equal(got, expected)
    through = cov.copy()
    covariance.transfer_gauge(through, before, after)
    np.testing.assert_array_equal(through, expected)
    fortran = np.asfortranarray(cov)
    covariance.transfer_gauge(fortran, before, after)
    np.testing.assert_array_equal(fortran, expected)
    np.testing.assert_array_equal(got, got.T)  # a symmetric covariance stays symmetric
