"""v 1 and v 2 edges in one fleet: the compass serves both (its headings in v 2); ``--wire 1`` edges publish lists."""

from __future__ import annotations

import pytest
from helpers import NO_SCOUT, connect_args, free_ports, listen_args, magnet_json

pytestmark = pytest.mark.integration


def test_v1_and_v2_edges_in_one_fleet_are_both_served(procs):
    compass_port, old_port, new_port = free_ports(3)
    procs.start("compass", "compass", *listen_args(compass_port))
    fleet = ["--emulate", "--devices", "3", "--rate", "50", "--batch", "10"]
    procs.start(
        "edge-old",
        "edge",
        "--device",
        "old",
        "--wire",
        "1",
        *fleet,
        *listen_args(old_port),
        *connect_args(compass_port),
    )
    procs.start("edge-new", "edge", "--device", "new", *fleet, *listen_args(new_port), *connect_args(compass_port))

    code, raws = magnet_json(
        "watch", "raw", "old-001", *NO_SCOUT, "--count", "2", "--duration", "20", *connect_args(old_port), timeout=90
    )
    assert code == 0 and len(raws) == 2 and all(m["v"] == 1 for m in raws)
    assert isinstance(raws[0]["mag_ut"][0], list)  # lists of numbers, as old subscribers read them
    code, headings = magnet_json(
        "watch", "heading", *NO_SCOUT, "--duration", "4", *connect_args(compass_port), timeout=90
    )
    served = {m["device"] for m in headings}
    assert served == {"old-000", "old-001", "old-002", "new-000", "new-001", "new-002"}
    assert all(m["v"] == 2 and len(m["heading_deg"]) == 10 for m in headings)
