"""The ROS 2 options services share (``--ros2``, ``--ros-domain``, ``--ros-namespace``), declared once as the fields of
``Ros2Settings`` (``services.common.options``)."""

from __future__ import annotations

import argparse
import dataclasses
from typing import Any

from magnet.ros2.names import DEFAULT_NAMESPACE, validate_namespace
from services.common.options import add_options, at_least, check_options, from_args, option

MAX_DOMAIN = 232  # ROS 2's domain ids, as for DDS
GROUP = "ROS 2 (rmw_zenoh)"


def _domain(value: Any) -> str | None:
    if at_least(0)(value) is not None or value > MAX_DOMAIN:
        return f"must be a whole number from 0 to {MAX_DOMAIN}"
    return None


def _namespace(value: Any) -> str | None:
    try:
        validate_namespace(value)
    except ValueError as exc:
        return f"is not a ROS namespace ({exc})"
    return None


@dataclasses.dataclass(frozen=True)
class Ros2Settings:
    """Whether to speak ROS 2, in which domain and namespace."""

    enabled: bool = option(False, "--ros2", help="speak ROS 2 (rmw_zenoh): see the group's description", group=GROUP)
    domain: int = option(
        0, "--ros-domain", metavar="ID", help="ROS_DOMAIN_ID of the ROS 2 graph", check=_domain, group=GROUP
    )
    namespace: str = option(
        DEFAULT_NAMESPACE,
        "--ros-namespace",
        metavar="NAMESPACE",
        help="ROS namespace of the topics",
        check=_namespace,
        group=GROUP,
    )

    def __post_init__(self) -> None:
        check_options(self)

    @classmethod
    def from_args(cls, args: argparse.Namespace) -> Ros2Settings:
        """The settings of the options ``add_ros2_arguments`` added, checked."""
        return from_args(cls, args)


def add_ros2_arguments(parser: argparse.ArgumentParser, what: str) -> None:
    """The ROS 2 options in their own group of the help, which says ``what`` ``--ros2`` does in this command."""
    add_options(parser, Ros2Settings, groups={GROUP: parser.add_argument_group(GROUP, f"--ros2: {what}")})
