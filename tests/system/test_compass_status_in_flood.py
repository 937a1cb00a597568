"""Issue 32: ``magnet bench soak`` found the compass's status answered within 1 s 258 times of 259, the one miss
after a flood of 20,000 new ids (the loop answered between drains). A real ``magnet compass --ros2`` flooded from
another process at the soak's rate: asked every 0.25 s during the flood, every status is answered within 1 s."""

from __future__ import annotations

import time

import pytest
from helpers import Processes, free_ports, listen_args, wait_for
from test_ros2_flood import ask_status, start_id_flood

from services.common.zenoh_session import ZenohSettings, open_session

pytestmark = pytest.mark.integration

FLOOD_IDS, FLOOD_RATE = 20_000, 5_000


def test_compass_status_is_answered_within_1_s_during_a_flood_of_new_ids(procs: Processes) -> None:
    [port] = free_ports(1)
    procs.start("compass", "compass", "--ros2", "--max-devices", "2000", *listen_args(port))
    client = ZenohSettings(mode="client", connect=(f"tcp/127.0.0.1:{port}",), no_multicast_scouting=True)
    with open_session(client) as session:
        wait_for(lambda: ask_status(session, 2.0)[0], 30, "the compass's status")
        flood = start_id_flood(port, FLOOD_IDS, FLOOD_RATE)
        waits: list[float | None] = []
        ages: list[float] = []
        try:
            while flood.poll() is None:
                status, took = ask_status(session, 2.0)
                waits.append(took if status is not None else None)
                if status is not None:
                    ages.append(status["status_age_s"])
                time.sleep(0.25)
        finally:
            _out, err = flood.communicate(timeout=60)
        assert flood.returncode == 0, err.decode()[-2000:]
        wait_for(lambda: (s := ask_status(session)[0]) and s["received_batches"] >= FLOOD_IDS, 60, "the flood taken")
    assert len(waits) >= 8 and None not in waits, waits
    assert max(w for w in waits if w is not None) < 1.0, waits
    assert max(ages) > 0.0, ages  # the answers say how old they are
