"""MAVLink 2 to the flight controller: HEARTBEAT at 1 Hz, ODOMETRY (id 331) at a set rate.

Fields follow ``INTERFACES.md``: position NED, ``q`` body→NED, velocity and angular rate in the
body (FRD) frame, 21-value upper-triangle covariances, ``reset_counter`` from the estimator,
``estimator_type = MAV_ESTIMATOR_TYPE_VIO`` and a 0–100 ``quality``. The link is any pymavlink
connection string; message signing (a shared 32-byte key) is optional, and when required,
unsigned or wrongly signed incoming messages are refused and counted. Incoming messages of
interest (e.g. the autopilot's ``GPS_RAW_INT``) are handed to callbacks.
"""

from __future__ import annotations

import asyncio
import logging
import math
from pathlib import Path
from typing import Any, Callable

import numpy as np

from vtolpose.config.outputs import parse_mavlink_url
from vtolpose.drivers.links.mavlink_wire import mavutil
from vtolpose.estimator.fusion import OutputPose
from vtolpose.estimator.core.rotation import quat_to_rot, skew
from vtolpose.service.runtime.status import FailureBook, pose_quality, stopped_within

log = logging.getLogger(__name__)

mav = mavutil.mavlink
COMPONENT_ID = mav.MAV_COMP_ID_VISUAL_INERTIAL_ODOMETRY  # 197
_TRIU = np.triu_indices(6)  # row-major upper-right triangle: 21 indices


class SigningKeyError(ValueError):
    """The signing key file is missing or not a 32-byte key."""


def read_signing_key(path: str | Path) -> bytes:
    """32 raw bytes, or 64 hexadecimal characters (whitespace ignored)."""
    path = Path(path)
    try:
        data = path.read_bytes()
    except OSError as exc:
        raise SigningKeyError(f"signing key file {path}: {exc.strerror or exc}") from None
    if len(data) == 32:
        return data
    text = data.decode("ascii", errors="replace").strip()
    if len(text) == 64:
        try:
            return bytes.fromhex(text)
        except ValueError:
            raise SigningKeyError(f"signing key file {path}: 64 characters, but not hexadecimal") from None
    raise SigningKeyError(f"signing key file {path}: expected 32 raw bytes or 64 hex characters, got {len(data)} bytes")


def euler_jacobian(q: np.ndarray) -> np.ndarray:
    """d(roll, pitch, yaw) / dθ for a world-frame attitude error θ (``R_true = Exp(θ) R``).

    With R = Rz(ψ) Ry(θ) Rx(φ), a world-frame rotation increment is
    ``δθ = [Rz Ry e_x | Rz e_y | e_z] · (δφ, δθ, δψ)``; this is that matrix's inverse, in closed
    form. It is singular at ±90° pitch, which a helicopter's estimator never reports:
    cos(pitch) is floored.
    """
    w, x, y, z = q.tolist()
    sp = min(max(2.0 * (w * y - z * x), -1.0), 1.0)
    cp = max(math.sqrt(1.0 - sp * sp), 1e-6)
    yaw = math.atan2(2.0 * (w * z + x * y), 1.0 - 2.0 * (y * y + z * z))
    cy, sy = math.cos(yaw), math.sin(yaw)
    return np.array([[cy / cp, sy / cp, 0.0], [-sy, cy, 0.0], [sp * cy / cp, sp * sy / cp, 1.0]])


def odometry_covariances(pose: OutputPose, r: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """ODOMETRY's two 6 × 6 covariances from the estimator's.

    Pose: the estimator's covariance is over ``[δp (NED), δθ (world-frame rotation)]``; MAVLink's
    states are ``x, y, z, roll, pitch, yaw``, so the attitude block is mapped through the Euler
    Jacobian (first order; at level attitude it is the identity, and yaw's variance is exact).
    Velocity: body-frame velocity ``v_B = Rᵀ v`` depends on the world velocity error and on the
    attitude error (``δv_B = Rᵀ δv + Rᵀ [v]× δθ``); the body rates are the bias-corrected gyro,
    uncorrelated with the velocity, with the gyro noise plus the bias variance.
    """
    cov9 = pose.cov9
    e = euler_jacobian(pose.q)
    pose_cov = np.empty((6, 6))
    pose_cov[0:3, 0:3] = cov9[0:3, 0:3]
    cross = cov9[0:3, 6:9] @ e.T
    pose_cov[0:3, 3:6] = cross
    pose_cov[3:6, 0:3] = cross.T
    pose_cov[3:6, 3:6] = e @ cov9[6:9, 6:9] @ e.T
    rt = (quat_to_rot(pose.q) if r is None else r).T
    jv = np.empty((3, 6))
    jv[:, 0:3] = rt
    jv[:, 3:6] = rt @ skew(pose.v)
    vel_cov = np.zeros((6, 6))
    vel_cov[0:3, 0:3] = jv @ cov9[3:9, 3:9] @ jv.T
    vel_cov[3, 3], vel_cov[4, 4], vel_cov[5, 5] = pose.omega_var.tolist()
    return pose_cov, vel_cov


def upper_triangle(cov: np.ndarray) -> list[float]:
    """The 21 values of the upper-right triangle, row-major; NaN first value when unknown."""
    values = cov[_TRIU]
    if not np.all(np.isfinite(values)):
        return [math.nan] + [0.0] * 20
    return values.tolist()


def odometry_fields(pose: OutputPose) -> dict[str, Any]:
    """Keyword arguments of ``odometry_send`` for ``pose`` (see :func:`odometry_covariances`)."""
    r = quat_to_rot(pose.q)
    pose_cov, vel_cov = odometry_covariances(pose, r)
    v_body = r.T @ pose.v
    return dict(
        time_usec=pose.t_ns // 1000,
        frame_id=mav.MAV_FRAME_LOCAL_NED,
        child_frame_id=mav.MAV_FRAME_BODY_FRD,
        x=float(pose.p[0]), y=float(pose.p[1]), z=float(pose.p[2]),
        q=[float(x) for x in pose.q],
        vx=float(v_body[0]), vy=float(v_body[1]), vz=float(v_body[2]),
        rollspeed=float(pose.omega_b[0]), pitchspeed=float(pose.omega_b[1]), yawspeed=float(pose.omega_b[2]),
        pose_covariance=upper_triangle(pose_cov),
        velocity_covariance=upper_triangle(vel_cov),
        reset_counter=pose.reset_counter % 256,
        estimator_type=mav.MAV_ESTIMATOR_TYPE_VIO,
        quality=pose_quality(pose),
    )


class MavlinkOutput:
    """One MAVLink link: sends HEARTBEAT and ODOMETRY, reads incoming messages for callbacks."""

    name = "mavlink"

    def __init__(
        self,
        url: str,
        system_id: int,
        component_id: int = COMPONENT_ID,
        rate_hz: float = 50.0,
        signing_key: bytes | None = None,
        require_signing: bool = False,
    ) -> None:
        self.url = url
        self.system_id = system_id
        self.component_id = component_id
        self.period_ns = int(1e9 / rate_hz) if rate_hz > 0 else 0
        self.signing_key = signing_key
        self.require_signing = require_signing
        self.handlers: dict[str, Callable[[Any], None]] = {}
        self.conn: Any = None
        self._next_odometry_t: int | None = None
        self._active = False
        self.stats = {"odometry_sent": 0, "heartbeats_sent": 0, "received": 0, "bad_data": 0, "serve_errors": 0}
        self.failures = FailureBook()

    def open(self) -> None:
        device, baud = parse_mavlink_url(self.url)
        self.conn = mavutil.mavlink_connection(
            device, baud=baud or 115200, source_system=self.system_id, source_component=self.component_id, autoreconnect=True
        )
        if self.signing_key is not None:
            # A callback that says no makes pymavlink count the refusal (reject_count).
            self.conn.setup_signing(self.signing_key, sign_outgoing=True,
                                    allow_unsigned_callback=lambda _mav, _msg_id: not self.require_signing)
        log.info("MAVLink link %s open (system %d, component %d%s)", self.url, self.system_id, self.component_id,
                 ", signed" if self.signing_key else "")

    def close(self) -> None:
        if self.conn is not None:
            self.conn.close()
            self.conn = None

    def publish(self, pose: OutputPose) -> bool:
        """Send ODOMETRY if the configured period (in sensor time) has passed. True when sent."""
        if self.conn is None:
            return False
        if self._next_odometry_t is not None and pose.t_ns < self._next_odometry_t:
            return False
        self._next_odometry_t = pose.t_ns + self.period_ns
        fields = odometry_fields(pose)
        self._active = fields["quality"] > 0
        self.conn.mav.odometry_send(**fields)
        self.stats["odometry_sent"] += 1
        return True

    def publish_status(self, status: dict[str, Any]) -> None:
        """The status document is Zenoh's; on MAVLink the HEARTBEAT's system state says it."""

    def heartbeat(self) -> None:
        if self.conn is None:
            return
        state = mav.MAV_STATE_ACTIVE if self._active else mav.MAV_STATE_STANDBY
        self.conn.mav.heartbeat_send(mav.MAV_TYPE_ONBOARD_CONTROLLER, mav.MAV_AUTOPILOT_INVALID, 0, 0, state)
        self.stats["heartbeats_sent"] += 1

    def poll(self) -> int:
        """Read every message waiting, without blocking; dispatch to ``handlers`` by type."""
        if self.conn is None:
            return 0
        n = 0
        while (msg := self.conn.recv_match(blocking=False)) is not None:
            kind = msg.get_type()
            if kind == "BAD_DATA":
                self.stats["bad_data"] += 1
                continue
            n += 1
            self.stats["received"] += 1
            handler = self.handlers.get(kind)
            if handler is not None:
                handler(msg)
        return n

    def link_stats(self) -> dict[str, int]:
        out = dict(self.stats)
        if self.conn is not None and self.signing_key is not None:
            signing = self.conn.mav.signing
            out.update(good_signatures=signing.goodsig_count, bad_signatures=signing.badsig_count,
                       unsigned_accepted=signing.unsigned_count, refused=signing.reject_count)
        return out

    async def serve(self, stop: asyncio.Event, poll_s: float = 0.02) -> None:
        """HEARTBEAT every second and incoming messages every ``poll_s`` until ``stop`` is set."""
        loop = asyncio.get_running_loop()
        next_beat = loop.time()
        while not stop.is_set():
            try:
                if loop.time() >= next_beat:
                    next_beat = max(next_beat + 1.0, loop.time())
                    self.heartbeat()
                self.poll()
            except Exception as exc:  # a socket error or a handler's bug: counted, the link keeps serving
                self.stats["serve_errors"] += 1
                self.failures.record(f"MAVLink link {self.url}", exc)
            await stopped_within(stop, poll_s)
