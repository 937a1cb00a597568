"""``magnet dashboard --foxglove HOST:PORT``: the fleet live in the Foxglove app, over the Foxglove WebSocket protocol
(foxglove-sdk's server on a private loopback address, behind ``foxglove_front``, which lets through only upgrades
with the dashboard's token from a known Host and Origin; loopback unless told otherwise).

Per device (its ROS name, ``magnet.ros2.names``), from each heading batch's last sample:

- ``/magnet/<device>/heading`` (JSON, schema ``magnet.Heading``): heading and true heading (deg, clockwise from
  north), ROS yaw (deg, counter-clockwise from east), pitch, roll, flags, calibrated, disturbed, calibration id;
- ``/magnet/<device>/field`` (JSON, schema ``magnet.Field``): the calibrated field in uT, body FLU, and |B|;
- ``/tf`` (``foxglove.FrameTransform``): the attitude, parent ``world`` (ENU) to child the device (FLU);
- ``/magnet/<device>/diagnostics`` (JSON, schema ``magnet.Diagnostics``), at most once a second: the level (0 OK,
  1 WARN, 2 ERROR) and message of ``/diagnostics``, the open alerts.

Frames are converted by ``magnet.ros2.frames`` (the same conversion as the ROS 2 topics).
"""

from __future__ import annotations

import contextlib
import logging
import threading
import time
from typing import Any

import foxglove
import numpy as np
import zenoh
from foxglove.channels import FrameTransformChannel
from foxglove.messages import FrameTransform, Quaternion, Timestamp, Vector3

from magnet import wire
from magnet.attitude.heading import HeadingFlag
from magnet.ros2 import compass as ros_compass
from magnet.ros2.frames import ros_yaw_deg, to_ros
from magnet.ros2.names import ros_name_of_device
from services.common.zenoh_session import drain, payload_bytes
from services.dashboard.foxglove_front import FoxgloveFront, FrontCheck, private_loopback_host

log = logging.getLogger("magnet.dashboard.foxglove")

MAX_DEVICES = 2000
DIAGNOSTICS_PERIOD_S = 1.0
_NUMBER, _STRING, _BOOL = {"type": "number"}, {"type": "string"}, {"type": "boolean"}


def _schema(title: str, **props: Any) -> dict[str, Any]:
    return {"title": title, "type": "object", "properties": props}


HEADING_SCHEMA = _schema(
    "magnet.Heading",
    t_ns=_NUMBER,
    heading_deg=_NUMBER,
    true_heading_deg=_NUMBER,
    ros_yaw_deg=_NUMBER,
    pitch_deg=_NUMBER,
    roll_deg=_NUMBER,
    flags=_NUMBER,
    calibrated=_BOOL,
    disturbed=_BOOL,
    calibration_id=_STRING,
)
FIELD_SCHEMA = _schema("magnet.Field", t_ns=_NUMBER, x_ut=_NUMBER, y_ut=_NUMBER, z_ut=_NUMBER, norm_ut=_NUMBER)
DIAGNOSTICS_SCHEMA = _schema("magnet.Diagnostics", level=_NUMBER, message=_STRING, alerts=_STRING)


def heading_views(batch: wire.HeadingBatch) -> tuple[dict[str, Any], dict[str, Any], tuple[float, ...]]:
    """(heading JSON, field JSON, attitude x y z w body FLU -> ENU (identity when unknown)) of the last sample of a
    heading batch."""
    i = len(batch) - 1
    quat = ros_compass.attitude_wxyz(
        None if batch.quat_wxyz is None else batch.quat_wxyz[i:],
        batch.true_heading_deg[i:],
        batch.pitch_deg[i:],
        batch.roll_deg[i:],
    )
    ros = to_ros(batch.field_ut[i:], np.zeros((1, 3)), None, quat)
    t_ns, flags = int(batch.t_ns[i]), int(batch.flags[i])
    heading = {
        "t_ns": t_ns,
        "heading_deg": float(batch.heading_deg[i]),
        "true_heading_deg": float(batch.true_heading_deg[i]),
        "ros_yaw_deg": float(ros_yaw_deg(batch.true_heading_deg[i:])[0]),
        "pitch_deg": float(batch.pitch_deg[i]),
        "roll_deg": float(batch.roll_deg[i]),
        "flags": flags,
        "calibrated": bool(flags & HeadingFlag.CALIBRATED),
        "disturbed": bool(batch.disturbed[i]),
        "calibration_id": batch.calibration_id,
    }
    field_ut = ros.field_t[0] * 1e6
    field = {"t_ns": t_ns, "x_ut": field_ut[0], "y_ut": field_ut[1], "z_ut": field_ut[2]}
    field = {k: float(v) for k, v in field.items()} | {"t_ns": t_ns, "norm_ut": float(np.linalg.norm(field_ut))}
    q = ros.quat_xyzw[0]
    rotation = tuple(float(c) for c in q) if np.isfinite(q).all() else (0.0, 0.0, 0.0, 1.0)
    return heading, field, rotation


class FoxgloveBridge:
    """Follows the fleet's headings and alerts on a Zenoh session and logs them to a Foxglove WebSocket server."""

    def __init__(
        self, session: zenoh.Session, prefix: str, host: str, port: int, token: str, allowed: frozenset[str]
    ) -> None:
        """Serve at ``host``:``port`` behind the front (``foxglove_front``): only upgrades naming an ``allowed`` host
        and carrying ``token`` (or its view token) reach the SDK's server, which listens on a private address."""
        private = private_loopback_host()
        self.server = foxglove.start_server(name="magnet", host=private, port=0)
        try:
            backend = (private, self.server.port)
            self.front = FoxgloveFront(host, port, backend, FrontCheck(token, allowed))
        except BaseException:
            self.server.stop()
            raise
        self.port = self.front.port
        self.declared = contextlib.ExitStack()
        fifo = zenoh.handlers.FifoChannel
        self.headings = self.declared.enter_context(session.declare_subscriber(f"{prefix}/*/heading", fifo(8192)))
        self.alerts = self.declared.enter_context(session.declare_subscriber(f"{prefix}/*/alert", fifo(256)))
        self.tf = FrameTransformChannel("/tf")
        self.channels: dict[str, tuple[foxglove.Channel, foxglove.Channel, foxglove.Channel]] = {}
        self.open_alerts: dict[str, set[str]] = {}
        self.next_diagnostics: dict[str, float] = {}
        self.dropped = 0
        self.stop = threading.Event()

    def __enter__(self) -> FoxgloveBridge:
        return self

    def __exit__(self, *exc: object) -> None:
        """Undeclare the subscribers (after ``stop`` and the end of ``run``)."""
        self.declared.close()

    def _channels(self, device: str) -> tuple[foxglove.Channel, foxglove.Channel, foxglove.Channel] | None:
        found = self.channels.get(device)
        if found is None and len(self.channels) < MAX_DEVICES:
            base = f"/magnet/{ros_name_of_device(device)}"
            found = self.channels[device] = (
                foxglove.Channel(f"{base}/heading", schema=HEADING_SCHEMA),
                foxglove.Channel(f"{base}/field", schema=FIELD_SCHEMA),
                foxglove.Channel(f"{base}/diagnostics", schema=DIAGNOSTICS_SCHEMA),
            )
        return found

    def step(self) -> int:
        """Log what arrived; the number of messages taken."""
        for sample in drain(self.alerts, 256):
            try:
                message = wire.unpack(payload_bytes(sample))
                alerts = self.open_alerts.setdefault(str(message["device"]), set())
                (alerts.discard if message.get("cleared") else alerts.add)(str(message["kind"]))
            except (ValueError, KeyError, TypeError):
                self.dropped += 1
        samples = drain(self.headings, 8192)
        for sample in samples:
            try:
                batch = wire.decode_heading(payload_bytes(sample))
            except wire.WireError:
                self.dropped += 1
                continue
            if len(batch):
                self._log(batch)
        return len(samples)

    def _log(self, batch: wire.HeadingBatch) -> None:
        channels = self._channels(batch.device)
        if channels is None:
            return
        heading, field, (x, y, z, w) = heading_views(batch)
        log_ns = time.time_ns()
        channels[0].log(heading, log_time=log_ns)
        channels[1].log(field, log_time=log_ns)
        transform = FrameTransform(
            timestamp=Timestamp(*divmod(heading["t_ns"], 1_000_000_000)),
            parent_frame_id="world",
            child_frame_id=ros_name_of_device(batch.device),
            translation=Vector3(x=0.0, y=0.0, z=0.0),
            rotation=Quaternion(x=x, y=y, z=z, w=w),
        )
        self.tf.log(transform, log_time=log_ns)
        now = time.monotonic()
        if now >= self.next_diagnostics.get(batch.device, 0.0):
            self.next_diagnostics[batch.device] = now + DIAGNOSTICS_PERIOD_S
            alerts = tuple(sorted(self.open_alerts.get(batch.device, ())))
            disturbed = float(np.mean(batch.disturbed)) if len(batch) else 0.0
            status = ros_compass.device_diagnostic(
                ros_compass.DeviceState(batch.device, batch.calibration_id, alerts=alerts, disturbed_share=disturbed)
            )
            message = {"level": status.level, "message": status.message, "alerts": ",".join(alerts)}
            channels[2].log(message, log_time=log_ns)

    def run(self) -> None:
        while not self.stop.is_set():
            if not self.step():
                self.stop.wait(0.01)
        self.front.close()
        self.server.stop()
