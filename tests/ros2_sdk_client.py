"""A ROS 2 peer nobody here wrote: zenoh-ros2-sdk (a pure-Python client of rmw_zenoh's protocol), run as its own
process by the ROS 2 tests. Its message definitions come from rosbags' Jazzy store, written out as ROS 2 ``.msg``
text, so it works offline (the SDK would otherwise clone message repositories); its type hashes are its own.

    python tests/ros2_sdk_client.py PORT subscribe TOPIC TYPE COUNT TIMEOUT_S   -> one JSON line per message
    python tests/ros2_sdk_client.py PORT topics                                 -> one JSON line: [[topic, [types]]]
    python tests/ros2_sdk_client.py PORT publish DEVICE SECONDS RATE_HZ          -> MagneticField + Imu of the simulator
    python tests/ros2_sdk_client.py - hash TYPE                                  -> the SDK's RIHS01 hash of TYPE

The session connects to tcp/127.0.0.1:PORT only, multicast scouting off.
"""

from __future__ import annotations

import json
import os
import sys
import time
from typing import Any

from rosbags.typesys import Stores, get_typestore
from rosbags.typesys.store import Nodetype

#: the SDK opens its own Zenoh session from this variable: no multicast, no listening (set only when run as a script,
#: never on import: a test that imports this module must not pass it on to every service the test run starts after)
SDK_CONFIG_OVERRIDE = "scouting/multicast/enabled=false;listen/endpoints=[]"

JAZZY = get_typestore(Stores.ROS2_JAZZY)


def _type_text(node: Any) -> str:
    kind, detail = node
    if kind == Nodetype.BASE:
        name, bound = detail
        return f"{name}<={bound}" if bound else name
    if kind == Nodetype.NAME:
        package, _, name = detail.split("/")
        return f"{package}/{name}"
    inner, size = detail
    if kind == Nodetype.ARRAY:
        return f"{_type_text(inner)}[{size}]"
    return f"{_type_text(inner)}[<={size}]" if size else f"{_type_text(inner)}[]"


def msg_text(ros_type: str) -> str:
    """The ROS 2 ``.msg`` text of a type of rosbags' Jazzy store."""
    consts, fields = JAZZY.fielddefs[ros_type]
    lines = [f"{kind} {name}={value}" for name, kind, value in consts]
    lines += [f"{_type_text(node)} {name}" for name, node in fields]
    return "\n".join(lines) + "\n"


def dependencies(ros_type: str, seen: dict[str, str] | None = None) -> dict[str, str]:
    """Every type ``ros_type`` refers to (transitively), as {name: .msg text}."""
    seen = {} if seen is None else seen
    for _, node in JAZZY.fielddefs[ros_type][1]:
        while node[0] in (Nodetype.ARRAY, Nodetype.SEQUENCE):
            node = node[1][0]
        if node[0] == Nodetype.NAME and node[1] not in seen:
            seen[node[1]] = msg_text(node[1])
            dependencies(node[1], seen)
    return seen


def sdk_hash(ros_type: str) -> str:
    from zenoh_ros2_sdk.utils import get_type_hash

    return str(get_type_hash(ros_type, msg_definition=msg_text(ros_type), dependencies=dependencies(ros_type)))


def _session(port: int) -> Any:
    from rosbags.typesys import get_types_from_msg
    from zenoh_ros2_sdk import ZenohSession

    session = ZenohSession.get_instance("127.0.0.1", port)
    nested: dict[str, str] = {}
    for ros_type in ("sensor_msgs/msg/Imu", "sensor_msgs/msg/MagneticField", "diagnostic_msgs/msg/DiagnosticArray"):
        nested.update(dependencies(ros_type))
    for name, text in nested.items():  # the nested types, before the message types
        session.store.register(get_types_from_msg(text, name))
    return session


def _plain(value: Any) -> Any:
    if hasattr(value, "__dataclass_fields__"):
        return {k: _plain(getattr(value, k)) for k in value.__dataclass_fields__ if k != "__msgtype__"}
    if hasattr(value, "tolist"):
        return value.tolist()
    if isinstance(value, list):
        return [_plain(v) for v in value]
    return value


def subscribe(port: int, topic: str, ros_type: str, count: int, timeout_s: float) -> None:
    from zenoh_ros2_sdk import ROS2Subscriber

    _session(port)
    got: list[Any] = []
    sub = ROS2Subscriber(
        topic,
        ros_type,
        callback=got.append,
        msg_definition=msg_text(ros_type),
        router_port=port,
        type_hash=sdk_hash(ros_type),
    )
    deadline = time.monotonic() + timeout_s
    while len(got) < count and time.monotonic() < deadline:
        time.sleep(0.05)
    sub.close()
    for msg in got[:count]:
        print(json.dumps(_plain(msg)), flush=True)


def topics(port: int) -> None:
    from zenoh_ros2_sdk import get_topic_names_and_types

    _session(port)
    print(json.dumps(get_topic_names_and_types(router_port=port, timeout=2.0)), flush=True)


def publish(port: int, device: str, seconds: float, rate_hz: float) -> None:
    """MagneticField (tesla, FLU) and Imu (m/s^2 and rad/s, FLU) of a simulated device turning through every
    attitude, stamped now, at ``rate_hz`` for ``seconds``."""
    import numpy as np
    from zenoh_ros2_sdk import ROS2Publisher

    from magnet.simulator import SimulatedDevices  # the project's simulator; its samples converted here to ROS 2's

    _session(port)
    mag_pub = ROS2Publisher(
        f"/{device}/mag",
        "sensor_msgs/msg/MagneticField",
        msg_definition=msg_text("sensor_msgs/msg/MagneticField"),
        router_port=port,
        type_hash=sdk_hash("sensor_msgs/msg/MagneticField"),
    )
    imu_pub = ROS2Publisher(
        f"/{device}/imu",
        "sensor_msgs/msg/Imu",
        msg_definition=msg_text("sensor_msgs/msg/Imu"),
        router_port=port,
        type_hash=sdk_hash("sensor_msgs/msg/Imu"),
    )
    step = SimulatedDevices(1, rate_hz=rate_hz, seed=7, gyro=True).step(int(seconds * rate_hz))
    types = JAZZY.types
    flip = np.array([1.0, -1.0, -1.0])  # body FRD -> FLU
    start = time.time_ns()
    samples = zip(step.mag_ut[0] * flip * 1e-6, step.acc_ms2[0] * flip, step.gyr_rads[0] * flip)
    for i, (m, a, w) in enumerate(samples):
        t_ns = start + int(i * 1e9 / rate_hz)
        header = types["std_msgs/msg/Header"](types["builtin_interfaces/msg/Time"](*divmod(t_ns, 10**9)), device)
        vector = types["geometry_msgs/msg/Vector3"]
        mag_pub.publish(header=header, magnetic_field=vector(*m), magnetic_field_covariance=np.zeros(9))
        imu_pub.publish(
            header=header,
            orientation=types["geometry_msgs/msg/Quaternion"](0.0, 0.0, 0.0, 1.0),
            orientation_covariance=np.array([-1.0] + [0.0] * 8),
            angular_velocity=vector(*w),
            angular_velocity_covariance=np.zeros(9),
            linear_acceleration=vector(*a),
            linear_acceleration_covariance=np.zeros(9),
        )
        time.sleep(max(0.0, (start + (i + 1) * 1e9 / rate_hz - time.time_ns()) / 1e9))
    mag_pub.close()
    imu_pub.close()


def main(argv: list[str]) -> None:
    port, command, *rest = argv
    if command == "hash":
        print(sdk_hash(rest[0]))
        return
    if command == "subscribe":
        subscribe(int(port), rest[0], rest[1], int(rest[2]), float(rest[3]))
    elif command == "topics":
        topics(int(port))
    elif command == "publish":
        publish(int(port), rest[0], float(rest[1]), float(rest[2]))
    from zenoh_ros2_sdk import ZenohSession

    ZenohSession.get_instance("127.0.0.1", int(port)).close()


if __name__ == "__main__":
    os.environ["ZENOH_CONFIG_OVERRIDE"] = SDK_CONFIG_OVERRIDE
    main(sys.argv[1:])
