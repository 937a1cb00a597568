"""``magnet compass --ros2``: the compass as a ROS 2 node on rmw_zenoh's own keys, beside its magnet messages.

Per device: ``sensor_msgs/msg/MagneticField`` on ``<NS>/<device>/mag`` and ``sensor_msgs/msg/Imu`` on
``<NS>/<device>/imu``, one message per sample; every second a ``diagnostic_msgs/msg/DiagnosticArray`` on
``/diagnostics``. A node token and one publisher token per topic make them appear in the ROS 2 graph. The messages
are built in ``magnet.ros2`` (frames, names, CDR); this module puts them. See ``docs/ros2.md``.

Shedding load (docs/front-door.md). Declaring a device's topics is the costly part (two publishers, two liveliness
tokens), it runs in the compass's loop, and Zenoh 1.10.2 keeps about 2 kB for good in the session (and the router) for
every publisher and token declared, even once undeclared (eclipse-zenoh/zenoh#1518). So: a device is given topics only
once it has sent ``PROMOTE_BATCHES`` batches (a flood's ids send one each; its batches before that, in earlier drains,
are counted as ``dropped[ros2:unproven]``; the devices counted are bounded, the least recently seen forgotten); at most
``--ros2-max-devices`` devices have topics; a new device beyond them takes the slot of the least recently published
device only when that one has been silent for ``IDLE_S`` (counted, ``sinks.ros2_topics_evicted``), else its samples stay
off ROS 2 (``dropped[ros2:device-limit]``); each drain declares new topics for at most ``DECLARE_BUDGET_S`` (at least
one device; the rest wait for a later drain, their samples counted as ``dropped[ros2:declare-budget]``); the devices
that have topics are published before any new one is declared, and the CDR is built only for the devices published.

Zenoh keeps that per key a session ever declared (about 9 kB a device; the same keys again cost nothing) until the
session closes. So behind a router the sink declares on a session of its own (``opener``), renewed once it declared
topics for ``DEVICES_PER_SESSION`` devices per slot, the devices that have topics declared again on the new one
(counted, ``sinks.ros2_sessions_renewed``): new ids (an edge restarted) leave at most that many devices' keys behind.
"""

from __future__ import annotations

import collections
import contextlib
import dataclasses
import functools
import logging
import time
from collections.abc import Callable, Mapping, Sequence
from typing import Self, cast

import numpy as np
import zenoh

from magnet import wire
from magnet.attitude.heading import HeadingFlag
from magnet.bounded import Recent
from magnet.compass import CompassCore, HeadingColumns
from magnet.drift import Alert
from magnet.ros2 import compass as ros_compass
from magnet.ros2 import messages, names
from magnet.vehicle import VehicleReport
from services.common.ros2_options import Ros2Settings
from services.common.zenoh_session import open_session, session_mode
from services.compass.settings import ZENOH_DEFAULTS, CompassSettings

log = logging.getLogger("magnet.compass.ros2")

DIAGNOSTICS_PERIOD_S = 1.0
#: a device with topics silent this long (s) may give its slot to a new device when every slot is taken
IDLE_S = 30.0
#: seconds of new topics' declarations at most per drain
DECLARE_BUDGET_S = 0.02
#: batches a device sends before it is given topics: a flood of new ids (one batch each) declares nothing, leaves no
#: declaration behind in Zenoh and takes no slot a real device waits for; a real device's first drain holds several
#: batches (20 a second from an edge), so it usually has its topics, and all its batches published, in its first drain
PROMOTE_BATCHES = 3
#: devices counted toward PROMOTE_BATCHES at most, per slot of ``--ros2-max-devices`` (the least recently seen
#: forgotten: in a flood of 5,000 new ids a second, 2,048 counted keep a device sending every 0.4 s or faster)
CANDIDATES_PER_SLOT = 8
#: devices one session of the sink declares topics for, per slot of ``--ros2-max-devices`` (the module): 4.6 MB at most
DEVICES_PER_SESSION = 2
#: vehicles whose compasses are compared in each DiagnosticArray at most (each comparison costs about 2 ms)
MAX_VEHICLE_DIAGNOSTICS = 16
DIAGNOSTICS_TOPIC = "/diagnostics"
CDR = zenoh.Encoding("application/cdr")
_DISTURBED = int(HeadingFlag.FIELD_DISTURBED | HeadingFlag.DIP_DISTURBED)


class _Topic:
    """One ROS 2 publisher: its key, liveliness token, GID and sequence number; ``close`` undeclares it."""

    def __init__(self, owner: Ros2Compass, topic: str, ros_type: str) -> None:
        owner.entities += 1
        endpoint = names.Endpoint("MP", topic, ros_type, messages.type_hash(ros_type), owner.entities)
        token = names.endpoint_token(owner.domain, owner.zid, 0, owner.namespace, owner.node, endpoint)
        self.key = names.topic_key(owner.domain, topic, ros_type, endpoint.type_hash)
        self.gid = names.gid_of(token)
        self._declared = contextlib.ExitStack()
        self._declared.enter_context(owner.session.liveliness().declare_token(token))
        # a declared publisher: about half the CPU of session.put per message (measured), as rmw_zenoh does
        self.publisher: zenoh.Publisher = self._declared.enter_context(
            owner.session.declare_publisher(self.key, encoding=CDR)
        )
        self.seq = 0

    def put(self, payload: bytes, t_ns: int) -> None:
        self.seq += 1
        self.publisher.put(payload, attachment=names.attachment_bytes(self.seq, t_ns, self.gid))

    def close(self) -> None:
        self._declared.close()


def build_drain(
    columns: wire.RawColumns, out: HeadingColumns, variances: list[float]
) -> list[tuple[list[bytes], list[bytes]]]:
    """The CDR of a drain: per device of ``columns``, (MagneticField messages, Imu messages), one per sample
    (``out``: the compass's ``HeadingColumns`` of them; ``variances``: per device, the field's variance in T^2)."""
    h = out.headings
    quat = ros_compass.attitude_wxyz(out.quat_wxyz, out.true_heading_deg, h.pitch_deg, h.roll_deg)
    return ros_compass.drain_messages(
        columns.devices,
        columns.bounds,
        columns.t_ns,
        h.field_ut,
        columns.acc_ms2,
        columns.gyr_rads,
        quat,
        variances,
        ros_compass.orientation_variance_rad2(out.heading_sigma_deg, out.tilt_sigma_deg),
    )


class Ros2Compass:
    """The ROS 2 sink of one compass (``services.compass.sinks.Sink``): a node ``<name>`` in ``--ros-namespace``,
    its publishers made per device as devices appear (at most ``max_devices``, the module's shedding), the
    diagnostics every second. A context manager: leaving it undeclares everything."""

    def __init__(
        self,
        session: zenoh.Session,
        settings: Ros2Settings,
        name: str,
        max_devices: int,
        opener: Callable[[], contextlib.AbstractContextManager[zenoh.Session]] | None = None,  # its own sessions
    ) -> None:
        self.domain, self.namespace = settings.domain, settings.namespace
        self.node = names.ros_name_of_device(name)
        self.opener, self.renewed, self.declared_devices = opener, 0, 0
        self._own = contextlib.ExitStack()  # the session of its own, when there is an opener
        self._declared = contextlib.ExitStack()
        self._open_node(session)
        self.max_devices = max_devices
        #: device -> (its two topics, when it was last published (monotonic s)), least recently published first
        self.devices: collections.OrderedDict[str, tuple[tuple[_Topic, _Topic], float]] = collections.OrderedDict()
        self.evicted = 0
        #: device without topics -> the batches it has sent (``PROMOTE_BATCHES``), least recently seen first
        self.candidates: Recent[str, int] = Recent(CANDIDATES_PER_SLOT * max_devices)
        self.disturbed: Recent[str, float] = Recent(max_devices)
        self.sigma: Recent[str, float] = Recent(max_devices)  # the median heading sigma of each device's last batch
        self.next_diagnostics = time.monotonic() + DIAGNOSTICS_PERIOD_S
        self.published = 0
        log.info("ROS 2: node %s/%s in domain %d (rmw_zenoh keys)", self.namespace, self.node, self.domain)

    def _open_node(self, session: zenoh.Session) -> None:
        """The node's token and the diagnostics' topic on ``session``, or on a new session of its own."""
        self.session = self._own.enter_context(self.opener()) if self.opener is not None else session
        self.zid, self.entities = str(self.session.info.zid()), 0
        token = names.node_token(self.domain, self.zid, 0, self.namespace, self.node)
        self._declared.enter_context(self.session.liveliness().declare_token(token))
        self.diagnostics = _Topic(self, DIAGNOSTICS_TOPIC, messages.DIAGNOSTIC_ARRAY)
        self._declared.callback(self.diagnostics.close)

    def _renew(self) -> None:
        """A new session of its own (what Zenoh kept for the old one's keys goes), every topic declared again."""
        for topics, _ in self.devices.values():
            _close_topics("", topics)
        self._declared.close()
        self._own.close()
        self._open_node(self.session)
        for device, (_, last_s) in self.devices.items():
            self.devices[device] = (self._topics(device), last_s)
        self.declared_devices = len(self.devices)
        self.renewed += 1
        log.info("ROS 2: a new session for the sink's topics (%d devices declared again)", len(self.devices))

    def _topics(self, device: str) -> tuple[_Topic, _Topic]:
        return (
            _Topic(self, names.topic_name(self.namespace, device, "mag"), messages.MAGNETIC_FIELD),
            _Topic(self, names.topic_name(self.namespace, device, "imu"), messages.IMU),
        )

    def _declare(self, device: str, now_s: float) -> bool:
        """Topics for a new device: in a free slot, or in the slot of the least recently published device when it
        has been silent for ``IDLE_S`` (counted); False when every slot is in use."""
        if len(self.devices) >= self.max_devices:
            oldest, (topics, last_s) = next(iter(self.devices.items()))
            if now_s - last_s < IDLE_S:
                return False
            del self.devices[oldest]
            self.disturbed.pop(oldest, None)
            _close_topics(oldest, topics)
            self.evicted += 1
        if self.opener is not None and self.declared_devices >= DEVICES_PER_SESSION * self.max_devices:
            self._renew()
        self.devices[device] = (self._topics(device), now_s)
        self.declared_devices += 1
        return True

    def known(self, devices: Sequence[str], now_s: float) -> list[bool]:
        """Per batch of a drain, whether its device has topics (each such device marked as just published)."""
        for device in set(devices).intersection(self.devices):
            self.devices[device] = (self.devices[device][0], now_s)
            self.devices.move_to_end(device)
        return [device in self.devices for device in devices]

    def declare_new(self, devices: Sequence[str], known: list[bool], core: CompassCore, now_s: float) -> list[bool]:
        """Per batch of a drain whose device had no topics (``known`` false), whether it has now: a device that has
        sent ``PROMOTE_BATCHES`` batches (this drain's counted) is declared while the slots and ``DECLARE_BUDGET_S``
        last (one device at least), the others counted as dropped in ``core.drops`` (``ros2:unproven`` per batch,
        ``ros2:device-limit`` and ``ros2:declare-budget`` per device and drain; the first of each logged)."""
        verdict: dict[str, bool] = {}
        sent_now = collections.Counter(device for device, was_known in zip(devices, known) if not was_known)
        deadline, declared, unproven = time.perf_counter() + DECLARE_BUDGET_S, False, 0
        for device, was_known in zip(devices, known):
            if was_known or device in verdict:
                continue
            sent = self.candidates.pop(device, 0) + sent_now[device]
            if sent < PROMOTE_BATCHES:
                self.candidates[device] = sent
                verdict[device] = False
                unproven += sent_now[device]
                continue
            if declared and time.perf_counter() >= deadline:  # one new device a drain at least: progress
                verdict[device] = False
                self.candidates[device] = sent  # proven: declared in a later drain
                self._refused(core, "ros2:declare-budget", device)
            elif self._declare(device, now_s):
                verdict[device] = declared = True
            else:
                verdict[device] = False
                self.candidates[device] = sent
                self._refused(core, "ros2:device-limit", device)
        if unproven and core.drops.count("ros2:unproven", unproven):
            log.info(
                "ROS 2: a device is given topics once it has sent %d batches; until then its batches are only "
                "counted (status dropped[ros2:unproven])",
                PROMOTE_BATCHES,
            )
        core.sink_counts.update(
            ros2_topics=len(self.devices), ros2_topics_evicted=self.evicted, ros2_sessions_renewed=self.renewed
        )
        return [not was_known and verdict[device] for device, was_known in zip(devices, known)]

    def admit(self, devices: Sequence[str], core: CompassCore, now_s: float) -> list[bool]:
        """Per batch of a drain, whether it goes to ROS 2 (``known``, then ``declare_new``)."""
        known = self.known(devices, now_s)
        return [a or b for a, b in zip(known, self.declare_new(devices, known, core, now_s))]

    def _refused(self, core: CompassCore, cause: str, device: str) -> None:
        if core.drops.count(cause):
            log.warning(
                "ROS 2: %s: %s kept off ROS 2 (%d devices have topics, --ros2-max-devices %d); further ones only "
                "counted (status dropped[%s])",
                cause,
                device,
                len(self.devices),
                self.max_devices,
                cause,
            )

    @classmethod
    def open(cls, session: zenoh.Session, settings: CompassSettings) -> Ros2Compass | None:
        """The compass's ROS 2 sink (``services.compass.sinks``), None without ``--ros2``."""
        if not settings.ros2.enabled:
            return None
        own = session_mode(settings.zenoh) == "client"  # behind a router: a session of its own, renewed
        opener = functools.partial(_open_own, settings) if own else None
        return cls(session, settings.ros2, settings.name, settings.ros2_max_devices, opener)

    def publish(self, columns: wire.RawColumns, out: HeadingColumns, core: CompassCore) -> None:
        """Put a MagneticField and an Imu per sample of ``columns`` (``out``: the compass's ``HeadingColumns`` of
        them; the core's calibrations in force give the field's covariance): the devices that have topics first,
        then the new ones given topics now (the module's shedding)."""
        now = time.monotonic()
        known = self.known(columns.devices, now)
        self._put(columns, out, core, known)
        if not all(known):
            self._put(columns, out, core, self.declare_new(columns.devices, known, core, now))

    def _put(self, columns: wire.RawColumns, out: HeadingColumns, core: CompassCore, chosen: list[bool]) -> None:
        """Put the messages of the batches ``chosen`` (their devices have topics); the CDR built for them only."""
        if not any(chosen):
            return
        if not all(chosen):
            columns, out = _select(columns, out, chosen)
        calibrations = core.calibrations.in_force
        h = out.headings
        cals = [calibrations.get(device) for device in columns.devices]
        variances = [
            ros_compass.field_variance_t2(c.calibration.quality.residual_rms_ut if c is not None else None)
            for c in cals
        ]
        built = build_drain(columns, out, variances)
        times = columns.t_ns.tolist()
        bounds = columns.bounds
        for i, (device, (mag, imu)) in enumerate(zip(columns.devices, built)):
            mag_topic, imu_topic = self.devices[device][0]
            for t, m, u in zip(times[bounds[i] : bounds[i + 1]], mag, imu):
                mag_topic.put(m, t)
                imu_topic.put(u, t)
            self.published += 2 * len(mag)
            flags = np.asarray(h.flags[bounds[i] : bounds[i + 1]], dtype=np.int64)
            self.disturbed[device] = float(np.mean((flags & _DISTURBED) != 0)) if len(flags) else 0.0
            sigma = out.heading_sigma_deg
            if sigma is not None and bounds[i + 1] > bounds[i]:
                self.sigma[device] = float(np.median(sigma[bounds[i] : bounds[i + 1]]))

    def tick(self, core: CompassCore) -> None:
        """Publish the diagnostics when their period has passed."""
        now = time.monotonic()
        if now < self.next_diagnostics or not len(self.disturbed):
            return
        self.next_diagnostics = now + DIAGNOSTICS_PERIOD_S
        reports = [r for v in core.vehicles.known()[:MAX_VEHICLE_DIAGNOSTICS] if (r := core.vehicle_report(v))]
        self.diagnose(core.calibrations.in_force, core.watch.open_alerts(), reports)

    def diagnose(
        self,
        calibrations: Mapping[str, wire.DeviceCalibration],
        open_alerts: list[Alert],
        vehicles: Sequence[VehicleReport] = (),
    ) -> None:
        """Put one DiagnosticArray: per device seen, its calibration in force, open alerts and disturbed share; per
        vehicle, its compasses compared (``ros_compass.vehicle_diagnostic``)."""
        alerts: dict[str, list[str]] = {}
        for alert in open_alerts:
            alerts.setdefault(alert.device, []).append(alert.kind.value)
        statuses = []
        for device in list(self.disturbed):
            cal = calibrations.get(device)
            quality = cal.calibration.quality if cal is not None else None
            state = ros_compass.DeviceState(
                device,
                cal.id if cal is not None else "",
                cal.calibration.method if cal is not None else "",
                quality.residual_rms_ut if quality is not None else None,
                quality.coverage if quality is not None else None,
                tuple(alerts.get(device, ())),
                self.disturbed.get(device) or 0.0,
                self.sigma.get(device),
            )
            statuses.append(ros_compass.device_diagnostic(state))
        statuses += [ros_compass.vehicle_diagnostic(report) for report in vehicles]
        t_ns = time.time_ns()
        self.diagnostics.put(messages.diagnostic_array_cdr(t_ns, statuses), t_ns)

    def __enter__(self) -> Self:
        return self

    def __exit__(self, *_exc: object) -> None:
        self.close()

    def close(self) -> None:
        for topics, _ in self.devices.values():
            _close_topics("", topics)
        self.devices.clear()
        self._declared.close()
        self._own.close()


def _open_own(settings: CompassSettings) -> contextlib.AbstractContextManager[zenoh.Session]:
    return open_session(settings.zenoh, ZENOH_DEFAULTS)


def _close_topics(_device: str, topics: tuple[_Topic, _Topic]) -> None:
    for topic in topics:
        topic.close()


def _select(columns: wire.RawColumns, out: HeadingColumns, keep: list[bool]) -> tuple[wire.RawColumns, HeadingColumns]:
    """The batches of a drain whose ``keep`` is true: their raw columns and their headings (every field that is per
    sample, (S, ...), cut to their rows; every list per batch, (B,), to them)."""
    mask = np.asarray(keep, dtype=bool)
    cut = _Cut(mask, np.repeat(mask, columns.counts))
    return cast(wire.RawColumns, cut(columns)), cast(HeadingColumns, cut(out))


class _Cut:
    """``_select``'s cut of one value (an array, a list or a dataclass of them, recursively) to the rows kept.

    A class, not a closure that calls itself: such a closure is a reference cycle (the function holds its own cell),
    which only the cycle collector frees, and it held the drain's masks until then. The compass raises the collector's
    first threshold (``service.GC_THRESHOLD``), so those waited for a full collection: in a soak's floods (a drain
    with unpublished batches each time) 300 of them piled up, several MB (docs/front-door.md)."""

    def __init__(self, mask: np.ndarray, rows: np.ndarray) -> None:
        self.mask, self.rows = mask, rows
        self.index = np.flatnonzero(mask).tolist()
        self.samples, self.batches = len(rows), len(mask)

    def __call__(self, value: object) -> object:
        if isinstance(value, np.ndarray):
            if value.shape[:1] == (self.samples,):
                return value[self.rows]
            return value[self.mask] if len(value) == self.batches else value
        if isinstance(value, list) and len(value) == self.batches:
            return [value[i] for i in self.index]
        if dataclasses.is_dataclass(value) and not isinstance(value, type):
            return dataclasses.replace(
                value, **{f.name: self(getattr(value, f.name)) for f in dataclasses.fields(value)}
            )
        return value
