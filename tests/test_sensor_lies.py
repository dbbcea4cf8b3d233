"""Sensors that lie about themselves: a GPS that overstates its accuracy, an IMU clock that steps.

Each damaged flight is replayed as a new user would (IMU + GPS) and must stay within 1.5 × the
clean flight's RMSE, with the lie said in the report (the noise the GPS really has, the steps undone).
"""

from __future__ import annotations

import re
import shutil
from pathlib import Path

import numpy as np
import pytest

from vtolpose.config import load_config
from vtolpose.drivers.files.clock_steps import reanchor
from vtolpose.drivers.files.dataset import GPS_CSV, IMU_CSV, Dataset
from vtolpose.drivers.simulator import simulate_flight
from vtolpose.drivers.simulator.export import write_flight
from vtolpose.service.bench.faults import FaultRun, traced_replay

DURATION_S = 50.0
T0_NS = 1_000_000_000  # the simulator's first stamp


@pytest.fixture(scope="module")
def flight(tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("lies") / "clean"
    write_flight(simulate_flight("landfill", DURATION_S, 1), root)
    return root


@pytest.fixture(scope="module")
def clean(flight) -> FaultRun:
    return traced_replay(Dataset.open(flight), load_config(), ["imu", "gps"])


def damaged(flight: Path, tmp_path: Path, rel: str, edit) -> Dataset:
    """A copy of ``flight`` whose ``rel`` rows went through ``edit(fields) -> fields``."""
    root = tmp_path / "damaged"
    shutil.copytree(flight, root)
    lines = (root / rel).read_text().splitlines()
    (root / rel).write_text("\n".join([lines[0], *(",".join(edit(line.split(","))) for line in lines[1:])]) + "\n")
    return Dataset.open(root)


def replayed(dataset: Dataset, *faults: str) -> FaultRun:
    return traced_replay(dataset, load_config(), ["imu", "gps"], list(faults))


def stepped_at(t_s: float, step_ns: int):
    return lambda f: [str(int(f[0]) + step_ns) if int(f[0]) - T0_NS >= t_s * 1e9 else f[0], *f[1:]]


def test_a_gps_claiming_impossible_accuracy_is_weighed_by_its_scatter(flight, clean, tmp_path):
    run = replayed(damaged(flight, tmp_path, GPS_CSV, lambda f: [*f[:4], "1e-300", "1e-300"]))
    est = run.result.estimator
    assert run.rmse() <= 1.5 * clean.rmse()
    assert est.reset_counter == 0
    noise = est.gps_noise.report()
    assert not noise["believed"] and 0.5 < noise["measured_sigma_h_m"] < 2.0  # the flight's GPS has σ 1 m
    assert noise["text"].startswith("GPS claims 0.000 m, behaves like")  # 1e-300 m, as the operator reads it
    assert any("behaves like" in e.message for e in est.events)
    assert est.counts_report()["gps"]["flagged"]["sigma_not_believed"] > 0


@pytest.mark.parametrize("rate_hz", [10, 1])
def test_a_lie_that_starts_in_flight_is_caught(flight, tmp_path, rate_hz):
    """From 15 s every fix claims 1e-300 m: the scatter of the fixes before is known, so the first lying fix
    is weighed with it (one that passed the gate with its 5 mm would collapse the covariance), and the
    claim is not believed from then on: no reset, at 10 Hz or at 1 Hz."""
    keep = (lambda f: int(f[0]) % 10**9 == 0) if rate_hz == 1 else (lambda f: True)
    root = tmp_path / f"gps{rate_hz}hz"
    shutil.copytree(flight, root)
    lines = (root / GPS_CSV).read_text().splitlines()
    (root / GPS_CSV).write_text("\n".join([lines[0], *(ln for ln in lines[1:] if keep(ln.split(",")))]) + "\n")
    honest = replayed(Dataset.open(root))
    run = replayed(Dataset.open(root), "gps-sigma:15:1000:1e-300")
    est = run.result.estimator
    assert est.health.reset_counts.get("gps_rejected", 0) == 0
    assert any("behaves like" in e.message and e.t_ns >= T0_NS + 15 * 10**9 for e in est.events)
    assert not est.gps_noise.report()["believed"]
    assert run.rmse() <= 1.5 * honest.rmse()


def test_honest_fixes_and_a_held_jump_keep_their_claims(flight, clean):
    """The check must not take an offset for noise: 10 s of fixes 20 m off are refused and reset to,
    as before, and honest fixes are believed."""
    assert clean.result.estimator.gps_noise.report()["believed"]
    run = replayed(Dataset.open(flight), "gps-jump:20:20,0,0:10")
    assert run.result.estimator.gps_noise.report()["believed"]
    assert run.result.estimator.health.reset_counts == {"gps_rejected": 2}


@pytest.mark.parametrize("step_ns", [10**18, -5 * 10**9])
def test_an_imu_clock_step_is_undone_on_the_gps_clock(flight, clean, tmp_path, step_ns):
    dataset = damaged(flight, tmp_path, IMU_CSV, stepped_at(16.0 if step_ns > 0 else 24.0, step_ns))
    run = replayed(dataset)
    assert run.rmse() <= 1.5 * clean.rmse()
    assert dataset.skipped[IMU_CSV] == 0  # no row dropped
    [step] = dataset.clock_steps[IMU_CSV]
    assert step.jump_ns == pytest.approx(step_ns, abs=10**7)
    assert run.result.estimator.reset_counter == 0


def test_what_is_no_clock_step_stays_as_it_was():
    t = T0_NS + np.arange(2000, dtype=np.int64) * 8_000_000
    one_bad = t.copy()
    one_bad[700] += 10**18  # a single corrupt stamp: the order check's
    assert reanchor(one_bad, int(t[-1])) == (pytest.approx(one_bad), [])
    gap = np.concatenate([t[:800], t[1200:]])  # 3.2 s of samples lost: the stream still ends with the others
    out, steps = reanchor(gap, int(t[-1]))
    assert steps == [] and np.array_equal(out, gap)
    out, steps = reanchor(gap, None)  # nothing to compare with: a jump forward stays a gap
    assert steps == []
    spliced = np.concatenate([t[:1000], t[:1000] - 3 * 10**9])
    out, [step] = reanchor(spliced, int(t[-1]))
    assert np.all(np.diff(out) == 8_000_000)


def test_while_the_imu_is_missing_the_held_pose_is_not_called_good():
    """The IMU stops for 3 s (host clock) while the GPS goes on: past imu_gap_reset_s (1 s) the status says the
    pose must not be used (quality 0, ODOMETRY -1); the IMU's return lifts that."""
    from vtolpose.estimator.filter import Estimator
    from vtolpose.service.runtime.loop import Runtime, RuntimeOptions
    from vtolpose.service.runtime.wiring import filter_options
    from runtime_helpers import PoseList, flight_samples

    flight = simulate_flight("landfill", 20.0, 2)
    est = Estimator(flight.calibration, filter_options(load_config(), flight.calibration.imu.noise))
    runtime = Runtime(est, RuntimeOptions(), outputs=[PoseList()])
    host_s = [100.0]
    runtime.status.clock = lambda: host_s[0]
    for sample in flight_samples(flight, 0.0, 12.0):
        runtime.handle(sample)
    assert runtime.status_document()["quality"] > 0
    host_s[0] += 3.0
    for sample in flight_samples(flight, 12.0, 15.0):
        if not hasattr(sample, "gyro"):  # the GPS alone
            runtime.handle(sample)
    doc = runtime.status_document()
    assert doc["quality"] == 0 and doc["pose_problem"].startswith("IMU missing")
    for sample in flight_samples(flight, 15.0, 17.0):
        runtime.handle(sample)
    doc = runtime.status_document()
    assert doc["quality"] > 0 and doc["pose_problem"] is None


def test_a_held_state_caps_the_quality_until_the_imu_returns(flight):
    """In a replay the filter sees the hole itself (a fix after 1 s without IMU): until the next IMU sample its
    health caps the quality at 0, and the status lists the IMU as missing."""
    from vtolpose.estimator.core.measurements import GpsFix
    from vtolpose.estimator.filter import Estimator
    from vtolpose.service.runtime.wiring import filter_options

    dataset = Dataset.open(flight)
    est = Estimator(dataset.calibration, filter_options(load_config(), dataset.calibration.imu.noise))
    imu, gps = dataset.imu(), dataset.gps()
    t_gap = T0_NS + 12 * 10**9
    for t, g, a in zip(imu.t_ns, imu.gyro, imu.accel):
        if t < t_gap:
            est.process_imu(int(t), g, a)
    fixes = [(int(t), p, h, v) for t, p, h, v in zip(gps.t_ns, gps.p_ned, gps.sigma_h, gps.sigma_v)]
    for t, p, h, v in fixes:
        if t_gap + 10**9 < t <= t_gap + 3 * 10**9:
            est.process_gps(GpsFix(t, p, float(h), float(v)))
    assert est.health.quality_cap(est.state.t_ns) == 0
    report = est.health.report(est.state.t_ns)
    assert "imu_missing" in report["degraded"] and report["sensors"]["imu"]["stale"]
    k = int(np.searchsorted(imu.t_ns, t_gap + 3 * 10**9, side="right"))
    est.process_imu(int(imu.t_ns[k]), imu.gyro[k], imu.accel[k])
    assert est.health.quality_cap(est.state.t_ns) > 0


def test_the_operator_is_told_what_the_gps_really_does():
    from vtolpose.service.outputs.mavlink_status import StatusEvents, mav

    events = StatusEvents()
    text = "GPS claims 0.005 m, behaves like 1.9 m"
    assert events.changes({"gps_noise": {"text": None}}) == []
    assert events.changes({"gps_noise": {"text": text}}) == [(mav.MAV_SEVERITY_WARNING, text)]
    assert events.changes({"gps_noise": {"text": text}}) == []
    assert events.changes({"gps_noise": {"text": None}})[0][0] == mav.MAV_SEVERITY_INFO


def test_a_live_receiver_that_lies_is_caught(flight, tmp_path, capsys):
    """The same lie live: the NMEA receiver's GST says 1 mm, the Crossbow IMU streams as usual; the run says
    what the fixes really do, and the pose is used rather than reset to every few seconds (caught before the
    start, or at the first reset when the fixes before the start were too few: it depends on the timing)."""
    emulators = pytest.importorskip("vtolpose.drivers.emulators")
    from vtolpose.service.cli import main

    lying = damaged(flight, tmp_path, GPS_CSV, lambda f: [*f[:4], "0.001", "0.001"]).root
    with emulators.Imu400Emulator.from_dataset(lying) as imu, emulators.NmeaEmulator.from_dataset(lying) as gps:
        config = tmp_path / "vehicle.yaml"
        config.write_text(f"sensors:\n  imu: {{port: {imu.port}}}\n  gps: {{type: nmea, port: {gps.port}}}\n"
                          f"  camera: {{type: none}}\nrun:\n  calibration_file: {lying / 'dataset.yaml'}\n"
                          "fusion:\n  delay_s: 0.5\n")
        code = main(["run", "--config", str(config), "--duration", "8"])
    out = capsys.readouterr().out
    assert code == 0, out
    assert "GPS accuracy claims not believed" in out and "GPS claims 0.001 m, behaves like" in out
    resets = re.search(r"filter resets: gps_rejected (\d+)", out)  # at most the one that catches it (timing)
    assert resets is None or int(resets.group(1)) <= 1, out


def test_camera_stamps_are_anchored_and_anchor_the_imu(flight, tmp_path):
    """Without GPS (a camera flight) the frame index is the IMU's other clock, and a step in it is undone too."""
    from vtolpose.drivers.files.dataset import CAM_CSV

    dataset = damaged(flight, tmp_path, IMU_CSV, stepped_at(16.0, 10**18))
    (dataset.root / GPS_CSV).unlink()
    period = 133_333_333
    stamps = [T0_NS + k * period for k in range(int(DURATION_S * 1e9) // period)]
    stepped = [t - 4 * 10**9 if t - T0_NS >= 30e9 else t for t in stamps]
    (dataset.root / CAM_CSV).parent.mkdir(parents=True, exist_ok=True)
    (dataset.root / CAM_CSV).write_text("#timestamp [ns],filename\n" + "".join(f"{t},{k}.png\n" for k, t in enumerate(stepped)))
    dataset = Dataset.open(dataset.root)
    imu = dataset.imu()
    assert len(dataset.clock_steps[IMU_CSV]) == 1 and imu.t_ns[-1] < T0_NS + 60 * 10**9
    frames = dataset.camera_frames()
    [step] = dataset.clock_steps[CAM_CSV]
    assert step.jump_ns == pytest.approx(-4 * 10**9 + period, abs=10)
    assert len(frames) == len(stamps) and dataset.skipped[CAM_CSV] == 0
    assert [t for t, _ in frames] == stamps and frames[-1][1].name == f"{len(stamps) - 1}.png"
