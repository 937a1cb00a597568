"""``magnet edge --ros2 --mag-topic T [--imu-topic T]``: a ROS 2 robot's own ``sensor_msgs/msg/MagneticField`` (and
``sensor_msgs/msg/Imu`` for acceleration and rates), taken from rmw_zenoh's keys on the edge's session, joined by
time (``magnet.ros2.pairing``) and fed to the pipeline as raw batches of ``--device``.

The source is a ROS 2 node in the graph (its node and subscription liveliness tokens). Malformed CDR, a message of
another type on the key and absurd values are dropped and counted by cause in the edge's status (``reads.errors``,
``errors_by_cause``); so are samples the pairing lets go (a backlog beyond its bytes, a field stamp that runs
backwards), each cause logged once; nothing from the network ends the edge. No MagneticField sample for
``SILENT_S`` (a wrong ``--mag-topic``, a robot that stopped) makes the source unhealthy (status ``healthy`` false,
``last_error`` says what to check, the device's unhealthy token) until one arrives.
"""

from __future__ import annotations

import contextlib
import logging
import time
from collections.abc import Iterator
from typing import Any

import zenoh

from magnet import wire
from magnet.retry import Health
from magnet.ros2 import messages, names
from magnet.ros2.pairing import SamplePairer
from services.common.zenoh_session import drain
from services.edge.settings import EdgeSettings
from services.edge.source import DeviceEvents, Stop

log = logging.getLogger("magnet.edge.ros2")

ROS2_SENSOR = "ros2"
POLL_S = 0.002
CHANNEL = 65536
PAIRING_DROPS = {
    "mag-backwards": "a MagneticField stamped at or before the one before it: the robot's clock ran backwards",
    "mag-backlog": "MagneticField samples waiting beyond the pairing's bound",
    "imu-backlog": "Imu samples waiting beyond the pairing's bound (no MagneticField of their time?)",
}
#: seconds without a MagneticField sample (since the start or the last one) after which the source is unhealthy
SILENT_S = 10.0


def _qualified(namespace: str, topic: str) -> str:
    """A topic name as given, made absolute in the namespace when relative."""
    return topic if topic.startswith("/") else f"{namespace.rstrip('/')}/{topic}"


class Ros2Source:
    """A ``services.edge.source.Source``: subscribes once given the session (``attach``), yields batches as they
    fill (``batches``), undeclares at ``close``."""

    def __init__(self, settings: EdgeSettings) -> None:
        if settings.mag_topic is None:
            raise ValueError("--ros2 needs --mag-topic TOPIC (a sensor_msgs/msg/MagneticField topic)")
        self.settings = settings
        self.ids = [settings.device]
        self.health = Health()
        self.pairer = SamplePairer(settings.imu_topic is not None, settings.batch)
        self.declared = contextlib.ExitStack()
        self.subs: dict[str, zenoh.Subscriber[zenoh.handlers.Handler[zenoh.Sample]]] = {}
        self.events: DeviceEvents | None = None
        self.last_sample_s = time.monotonic()  # the start counts as a sample: SILENT_S to the first
        self._seen_samples = 0

    def attach(self, session: zenoh.Session, events: DeviceEvents) -> None:
        """Declare the subscriptions (data keys of the exact type hash) and the node's liveliness tokens."""
        self.events = events
        ros = self.settings.ros2
        zid, node = str(session.info.zid()), "magnet_edge_" + names.ros_name_of_device(self.settings.device)
        self.declared.enter_context(
            session.liveliness().declare_token(names.node_token(ros.domain, zid, 0, ros.namespace, node))
        )
        topics = {messages.MAGNETIC_FIELD: self.settings.mag_topic, messages.IMU: self.settings.imu_topic}
        for entity, (ros_type, topic) in enumerate(topics.items(), start=1):
            if topic is None:
                continue
            topic = _qualified(ros.namespace, topic)
            endpoint = names.Endpoint("MS", topic, ros_type, messages.type_hash(ros_type), entity)
            token = names.endpoint_token(ros.domain, zid, 0, ros.namespace, node, endpoint)
            self.declared.enter_context(session.liveliness().declare_token(token))
            key = names.topic_key(ros.domain, topic, ros_type, endpoint.type_hash)
            self.subs[ros_type] = self.declared.enter_context(
                session.declare_subscriber(key, zenoh.handlers.FifoChannel(CHANNEL))
            )
            log.info("ROS 2: subscribed to %s (%s) on %s", topic, ros_type, key)

    def status(self) -> dict[str, Any]:
        return self.health.as_dict()

    def close(self) -> None:
        self.declared.close()

    def _take(self, ros_type: str, now_s: float) -> int:
        handler = self.subs.get(ros_type)
        samples: list[zenoh.Sample] = [] if handler is None else drain(handler, 10_000)
        for sample in samples:
            self.health.attempts += 1
            try:
                data = sample.payload.to_bytes()
                if ros_type == messages.IMU:
                    self.pairer.add_imu(messages.decode_imu(data))
                else:
                    self.pairer.add_mag(messages.decode_magnetic_field(data), now_s)
                    self.health.samples += 1
            except ValueError as exc:
                self._count(f"{ros_type.rsplit('/', 1)[-1]}: {exc}", "malformed-" + ros_type.rsplit("/", 1)[-1])
        return len(samples)

    def _count(self, error: str, cause: str) -> None:
        health = self.health
        health.errors += 1
        health.last_error = error
        health.errors_by_cause[cause] = health.errors_by_cause.get(cause, 0) + 1
        if health.errors_by_cause[cause] == 1:
            log.warning("dropping ROS 2 messages (%s); further ones only counted", error)

    def watch(self, now_s: float) -> None:
        """Health from the field samples (module docstring): unhealthy after ``SILENT_S`` without one, healthy again
        at the next; each change told to the edge (its unhealthy token) and logged."""
        health = self.health
        if health.samples != self._seen_samples:
            self._seen_samples, self.last_sample_s = health.samples, now_s
        silent = now_s - self.last_sample_s > SILENT_S
        if silent == (not health.healthy):
            return
        health.healthy = not silent
        if silent:
            health.last_error = (
                f"no MagneticField sample on {self.settings.mag_topic} for {SILENT_S:g} s ({health.samples} in all): "
                "check --mag-topic (and --ros-namespace, --ros-domain) against `ros2 topic list`, and that the robot "
                "publishes"
            )
            log.warning("ROS 2: %s", health.last_error)
        else:
            log.info("ROS 2: MagneticField samples on %s again", self.settings.mag_topic)
        if self.events is not None:
            self.events.on_health(health.healthy, health.last_error)

    def _pairing_drops(self) -> None:
        """The pairing's drops into the status's causes, each cause logged the first time."""
        for cause, count in self.pairer.dropped.items():
            if cause not in self.health.errors_by_cause:
                why = PAIRING_DROPS.get(cause, cause)
                log.warning("dropping ROS 2 samples (%s: %s); further ones only counted", cause, why)
            self.health.errors_by_cause[cause] = count

    def batches(self, stop: Stop) -> Iterator[list[wire.RawBatch]]:
        """One list of one batch each time a batch fills, until ``stop()``."""
        seq = 0
        while not stop():
            now = time.monotonic()
            got = self._take(messages.IMU, now) + self._take(messages.MAGNETIC_FIELD, now)
            self._pairing_drops()
            self.watch(now)
            for joined in self.pairer.batches(now):
                yield [
                    wire.RawBatch(
                        self.settings.device,
                        seq,
                        ROS2_SENSOR,
                        joined.t_ns,
                        joined.mag_ut,
                        joined.acc_ms2,
                        gyr_rads=joined.gyr_rads,
                        location=self.settings.location,
                    )
                ]
                seq += 1
            if not got:
                time.sleep(POLL_S)
