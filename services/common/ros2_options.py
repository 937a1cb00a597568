"""The ROS 2 options services share (``--ros2``, ``--ros-domain``, ``--ros-namespace``) and their settings."""

from __future__ import annotations

import argparse
import dataclasses

from magnet.ros2.names import DEFAULT_NAMESPACE, validate_namespace

MAX_DOMAIN = 232  # ROS 2's domain ids, as for DDS


def add_ros2_arguments(parser: argparse.ArgumentParser, what: str) -> None:
    group = parser.add_argument_group("ROS 2 (rmw_zenoh)")
    group.add_argument("--ros2", action="store_true", help=what)
    group.add_argument("--ros-domain", type=int, default=0, help="ROS_DOMAIN_ID of the ROS 2 graph (default 0)")
    group.add_argument(
        "--ros-namespace", default=DEFAULT_NAMESPACE, help=f"ROS namespace of the topics (default {DEFAULT_NAMESPACE})"
    )


@dataclasses.dataclass(frozen=True)
class Ros2Settings:
    """Whether to speak ROS 2, in which domain and namespace."""

    enabled: bool = False
    domain: int = 0
    namespace: str = DEFAULT_NAMESPACE

    def __post_init__(self) -> None:
        if isinstance(self.domain, bool) or not isinstance(self.domain, int) or not 0 <= self.domain <= MAX_DOMAIN:
            raise ValueError(f"--ros-domain must be a whole number from 0 to {MAX_DOMAIN}, got {self.domain!r}")
        validate_namespace(self.namespace)

    @classmethod
    def from_args(cls, args: argparse.Namespace) -> Ros2Settings:
        return cls(bool(args.ros2), args.ros_domain, args.ros_namespace)
