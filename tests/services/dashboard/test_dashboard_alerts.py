"""A dashboard started after a device opened two drift alerts shows both: the open alerts a compass answers share
the device's key, so the dashboard asks without Zenoh's consolidation (which kept one). A real queryable in another
process answers, as a compass does."""

import subprocess
import sys
import textwrap
import time

import pytest
import zenoh
from helpers import _loopback_client_config

from magnet.drift import Alert, AlertKind
from services.common.zenoh_session import free_ports
from services.dashboard.ingest import Ingest
from services.dashboard.state import FleetState

pytestmark = pytest.mark.integration

ALERTS = [
    Alert("dev-1", AlertKind.FIELD_STRENGTH, 1_000_000_000, 58.2, 50.1, ""),
    Alert("dev-1", AlertKind.DIP, 2_000_000_000, 71.0, 66.0, ""),
]

COMPASS = """
import sys, zenoh
from magnet import wire
conf = zenoh.Config()
conf.insert_json5("listen/endpoints", '["tcp/127.0.0.1:{port}"]')
conf.insert_json5("scouting/multicast/enabled", "false")
messages = {messages!r}
with zenoh.open(conf) as session:
    def answer(query):
        for message in messages:
            query.reply("magnet/dev-1/alert", wire.pack(message))
    with session.declare_queryable("magnet/*/alert", answer):
        print("ready", flush=True)
        sys.stdin.read()
"""


def test_a_dashboard_started_after_two_alerts_opened_shows_both():
    (port,) = free_ports(1)
    script = textwrap.dedent(COMPASS).format(port=port, messages=[a.to_message() for a in ALERTS])
    compass = subprocess.Popen([sys.executable, "-c", script], stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)
    try:
        assert compass.stdout.readline().strip() == "ready"
        state = FleetState(None)
        with zenoh.open(_loopback_client_config(port)) as session, Ingest(session, "magnet", state) as ingest:
            deadline = time.monotonic() + 10
            while time.monotonic() < deadline and len(getattr(state.rows.get("dev-1"), "drift", ())) < 2:
                ingest.asked_s = -1e9  # ask again until both are in
                ingest._ask_calibrations()
                time.sleep(0.3)
                ingest._take_replies()
        assert set(state.rows["dev-1"].drift) == {"field_strength", "dip"}
    finally:
        compass.stdin.close()
        compass.wait(timeout=10)
        compass.stdout.close()
