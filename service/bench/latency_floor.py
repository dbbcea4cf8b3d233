"""How low the pose's handling can go on this machine: ``runtime-latency``'s camera-process run three times, with
parts of the per-sample work stood in for by what costs next to nothing.

1. as it is;
2. the outputs' encodings stood in for: each output sends the bytes it made for the first measured pose again
   (MAVLink still framed, checksummed and sent per pose; the Zenoh document put as it was);
3. the prediction too: the output predictor no longer steps per sample (the sample is still queued for the
   filter) and the first measured pose is handed out again.

What is left in (3) is the runtime's own handling: the loop taking the sample, the publish calls, the two sends,
the pose history's row. If that alone is near the 0.2-ms target, no faster estimator or encoder can meet the
target on this machine; if it is well below, the gap between (3) and (1) is what a compiled pose path could win.
The stand-ins touch only the bench's own runtime (attributes of its instances), never the classes.
"""

from __future__ import annotations

from typing import Any

from vtolpose.service.bench.rows import Row
from vtolpose.service.bench.runtime import figure, latency_run
from vtolpose.service.outputs.mavlink_odometry import ODOMETRY_CRC_EXTRA, ODOMETRY_ID, odometry_fields, odometry_payload
from vtolpose.service.outputs.mavlink_output import MavlinkOutput
from vtolpose.service.outputs.pose_json import PoseJson
from vtolpose.service.outputs.zenoh import ZenohOutput

STAND_INS = ("encodings", "prediction")
RUNS = (("as is", ()), ("encodings stood in", ("encodings",)), ("encodings and prediction stood in", STAND_INS))


class _FirstDocument:
    """A pose document encoder that writes the first pose's document and hands it out again."""

    def __init__(self, encode: Any) -> None:
        self._encode = encode
        self.document: str | None = None

    def __call__(self, pose: Any, seq: int, origin: Any) -> str:
        if self.document is None:
            self.document = self._encode(pose, seq, origin)
        return self.document

    def prepare(self, pose_cov: Any) -> None:
        """Nothing to write ahead: the document is the first one."""


def _first_payloads(out: MavlinkOutput) -> Any:
    """``out.publish`` sending, at every pose, each open endpoint's ODOMETRY payload of the first pose (framed per
    send; no rate schedule: the bench asks for a pose at every sample)."""
    payloads: dict[str, bytes] = {}

    def publish(pose: Any) -> bool:
        for endpoint in out.endpoints:
            if endpoint.transport is None:
                continue
            profile = endpoint.profile
            if profile.name not in payloads:
                shown, frame_id, resets = out.frames[profile.name].present(pose)
                payloads[profile.name] = odometry_payload(odometry_fields(shown, profile, frame_id, resets))
            endpoint.send_packed(ODOMETRY_ID, ODOMETRY_CRC_EXTRA, payloads[profile.name], "odometry_sent")
        return bool(payloads)

    return publish


def stand_in(runtime: Any, parts: tuple[str, ...]) -> None:
    """Replace ``parts`` (of :data:`STAND_INS`) of ``runtime``'s per-sample work, on its instances only: after the
    warm-up, so that the first pose exists."""
    unknown = set(parts) - set(STAND_INS)
    if unknown:
        raise ValueError(f"unknown stand-in(s) {sorted(unknown)}; choose from {', '.join(STAND_INS)}")
    if "encodings" in parts:
        for out in runtime.outputs:
            if isinstance(out, MavlinkOutput):
                out.publish = _first_payloads(out)
            elif isinstance(out, ZenohOutput):
                if not isinstance(getattr(out, "_pose_json", None), PoseJson):
                    raise TypeError("the Zenoh output no longer encodes its poses through _pose_json: update this stand-in")
                out._pose_json = _FirstDocument(out._pose_json)  # the encoder the output calls per pose
    if "prediction" in parts:
        fusion = runtime.fusion
        if not callable(getattr(fusion, "_step", None)):
            raise TypeError("the fusion core no longer steps its prediction through _step: update this stand-in")
        first = fusion.output()
        if first is None:
            raise ValueError("the prediction can be stood in for only once the filter has started")
        # No step per sample (the sample is still counted and queued for the filter, which fuses as before).
        fusion._step = lambda pred, t, gyro, accel: None
        fusion.output = lambda: first


def bench_latency_floor(duration_s: float = 15.0, rounds: int = 2) -> list[Row]:
    """The pose's handling with its encodings, then its prediction too, stood in for (camera process, SIFT at 7.5 Hz): the floor under the 0.2-ms target."""
    in_process = {"fusion": {"camera_process": True}}
    rows: list[Row] = []
    handling: dict[str, list[float]] = {label: [] for label, _ in RUNS}
    for round_ in range(rounds):  # the three in turn, so that a slow minute costs each
        for label, parts in RUNS:
            run = latency_run(duration_s, None, f"{label}, round {round_ + 1}", in_process,
                              after_warm_up=lambda runtime, parts=parts: stand_in(runtime, parts))
            # With work stood in for, a figure is a floor to read, not the service's against its target.
            rows += [Row(*row[:4]) for row in run] if parts else run
            handling[label].append(figure(run, "handling on the loop, p50"))
    base = handling[RUNS[0][0]]
    for label, _ in RUNS[1:]:
        ratios = [h / b for h, b in zip(handling[label], base)]
        rows.append(Row(f"handling p50, {label} / as is", min(ratios), "x",
                        f"each round: {', '.join(f'{h:.0f} against {b:.0f} us' for h, b in zip(handling[label], base))}"
                        f" (ratios {', '.join(f'{r:.2f}' for r in ratios)}); the lower shown"))
    return rows
