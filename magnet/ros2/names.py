"""ROS 2 names and rmw_zenoh's keys: device ids as ROS names (a reversible rule), topic names, the data key
expression of a topic, the ``@ros2_lv`` liveliness tokens of a node and its publishers and subscriptions, and the
attachment that goes with every sample. The format is described in ``docs/ros2.md``."""

from __future__ import annotations

import dataclasses
import hashlib
import re
import struct

__all__ = [
    "ADMIN_SPACE",
    "DEFAULT_NAMESPACE",
    "DEFAULT_QOS",
    "Attachment",
    "Endpoint",
    "attachment_bytes",
    "dds_type_name",
    "device_from_ros_name",
    "endpoint_token",
    "gid_of",
    "node_token",
    "ros_name_of_device",
    "topic_key",
    "topic_name",
    "validate_namespace",
]

ADMIN_SPACE = "@ros2_lv"
DEFAULT_NAMESPACE = "/magnet"
#: reliable, volatile, keep last 10, no deadline, lifespan or liveliness lease: rmw_zenoh's compact QoS text with
#: the fields left at their default empty
DEFAULT_QOS = "::,10:,:,:,,"
_ESCAPE = "x"  # a ROS name starting with it is an encoded device id
_PLAIN = re.compile(r"[A-Za-z][A-Za-z0-9]*(_[A-Za-z0-9]+)*")
_ENCODED = re.compile(r"x([A-Za-z0-9]|_[0-9a-f]{2})*")
_TOKEN = re.compile(r"[A-Za-z_][A-Za-z0-9_]*")


def ros_name_of_device(device: str) -> str:
    """The ROS name token of a device id. An id that is already a clean ROS token (a letter, then letters, digits
    and single inner underscores) and does not start with ``x`` stays as it is; any other is ``x`` followed by the
    id with every character other than an ASCII letter or digit written as ``_`` and the two lowercase hex digits
    of each of its UTF-8 bytes (``imu-1`` -> ``ximu_2d1``, ``xsens`` -> ``xxsens``). Reversed by
    ``device_from_ros_name``."""
    if _PLAIN.fullmatch(device) and not device.startswith(_ESCAPE):
        return device
    out = [_ESCAPE]
    for char in device:
        if char.isascii() and char.isalnum():
            out.append(char)
        else:
            out.extend(f"_{byte:02x}" for byte in char.encode())
    return "".join(out)


def device_from_ros_name(name: str) -> str:
    """The device id of a ROS name token made by ``ros_name_of_device``; ValueError for a name it cannot make."""
    if not name.startswith(_ESCAPE):
        if not _PLAIN.fullmatch(name):
            raise ValueError(f"{name!r} is not a ROS name that magnet makes for a device")
        return name
    if not _ENCODED.fullmatch(name):
        raise ValueError(f"{name!r} is not a device id encoded by magnet (x, then letters, digits and _hh escapes)")
    body, data, i = name[1:], bytearray(), 0
    while i < len(body):
        if body[i] == "_":
            data.append(int(body[i + 1 : i + 3], 16))
            i += 3
        else:
            data.extend(body[i].encode())
            i += 1
    try:
        return data.decode()
    except UnicodeDecodeError as exc:
        raise ValueError(f"{name!r} does not decode to a UTF-8 device id") from exc


def validate_namespace(namespace: str) -> str:
    """A ROS namespace: ``/`` or ``/`` followed by tokens separated by ``/``; ValueError otherwise."""
    if namespace == "/":
        return namespace
    tokens = namespace.split("/")
    if tokens[0] != "" or not all(_TOKEN.fullmatch(t) and not t[0].isdigit() for t in tokens[1:]):
        raise ValueError(
            f"--ros-namespace must be '/' or like '/magnet' or '/robot_1/compass' (tokens of letters, digits and "
            f"_ not starting with a digit), got {namespace!r}"
        )
    return namespace


def topic_name(namespace: str, device: str, leaf: str) -> str:
    """``<namespace>/<device as a ROS name>/<leaf>``, e.g. ``/magnet/ximu_2d1/mag``."""
    return f"{namespace.rstrip('/')}/{ros_name_of_device(device)}/{leaf}"


def dds_type_name(ros_type: str) -> str:
    """``sensor_msgs/msg/Imu`` -> ``sensor_msgs::msg::dds_::Imu_``, the type name rmw_zenoh puts in keys."""
    package, kind, name = ros_type.split("/")
    return f"{package}::{kind}::dds_::{name}_"


def topic_key(domain: int, topic: str, ros_type: str, type_hash: str) -> str:
    """The data key expression of a topic: ``<domain>/<topic without its leading />/<DDS type>/<RIHS01 hash>``."""
    return f"{domain}/{topic.strip('/')}/{dds_type_name(ros_type)}/{type_hash}"


def _mangle(name: str) -> str:
    """A name inside one chunk of a liveliness token: ``/`` written ``%``, the empty name ``%``."""
    return name.replace("/", "%") if name not in ("", "/") else "%"


@dataclasses.dataclass(frozen=True)
class Endpoint:
    """A publisher ("MP") or subscription ("MS") of a node, as the ROS 2 graph sees it."""

    kind: str
    topic: str
    ros_type: str
    type_hash: str
    entity_id: int
    qos: str = DEFAULT_QOS

    def __post_init__(self) -> None:
        if self.kind not in ("MP", "MS"):
            raise ValueError(f"endpoint kind must be MP or MS, got {self.kind!r}")


def node_token(domain: int, zid: str, node_id: int, namespace: str, node: str) -> str:
    """The liveliness token of a node: ``@ros2_lv/<domain>/<zid>/<nid>/<nid>/NN/%/<namespace>/<node>`` (enclave
    ``%``, none)."""
    return f"{ADMIN_SPACE}/{domain}/{zid}/{node_id}/{node_id}/NN/%/{_mangle(namespace)}/{_mangle(node)}"


def endpoint_token(domain: int, zid: str, node_id: int, namespace: str, node: str, endpoint: Endpoint) -> str:
    """The liveliness token of a publisher or subscription of that node: the node's chunks (with the endpoint's id
    in place of the second node id and its kind for NN), then topic, DDS type, type hash and QoS."""
    return (
        f"{ADMIN_SPACE}/{domain}/{zid}/{node_id}/{endpoint.entity_id}/{endpoint.kind}/%/{_mangle(namespace)}/"
        f"{_mangle(node)}/{_mangle(endpoint.topic)}/{dds_type_name(endpoint.ros_type)}/{endpoint.type_hash}/"
        f"{endpoint.qos}"
    )


def gid_of(token: str) -> bytes:
    """The 16-byte source GID of an endpoint: the first 16 bytes of the SHA-256 of its liveliness token."""
    return hashlib.sha256(token.encode()).digest()[:16]


_ATTACHMENT_HEAD = struct.Struct("<QqB")


def attachment_bytes(seq: int, t_ns: int, gid: bytes) -> bytes:
    """The attachment of one sample (see ``Attachment``), without making the record: for the publishing loop."""
    return _ATTACHMENT_HEAD.pack(seq, t_ns, len(gid)) + gid


@dataclasses.dataclass(frozen=True)
class Attachment:
    """What rmw_zenoh attaches to every sample: the publisher's sequence number, the source time (ns since the
    epoch) and the publisher's GID. Bytes: u64 LE, i64 LE, u8 length, the GID."""

    seq: int
    t_ns: int
    gid: bytes

    def to_bytes(self) -> bytes:
        return attachment_bytes(self.seq, self.t_ns, self.gid)

    @classmethod
    def from_bytes(cls, data: bytes) -> Attachment:
        """ValueError for an attachment too short or whose GID runs past its end."""
        if len(data) < 17:
            raise ValueError(f"rmw_zenoh attachment of {len(data)} bytes, at least 17 expected")
        seq, t_ns, size = struct.unpack_from("<QqB", data)
        if len(data) != 17 + size:
            raise ValueError(f"rmw_zenoh attachment of {len(data)} bytes with a GID of {size}")
        return cls(seq, t_ns, bytes(data[17:]))
