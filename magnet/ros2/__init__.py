"""ROS 2 without a bridge: frames (REP-103), names, rmw_zenoh key expressions and liveliness tokens, and the CDR
messages magnet publishes and reads. Pure: no zenoh, no clock. See ``docs/ros2.md``."""
