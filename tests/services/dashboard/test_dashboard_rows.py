"""The dashboard forgets: a row nothing was heard of for ``--forget-after`` (its liveliness token gone) is forgotten,
rows are bounded by ``--max-devices`` (least recently heard of first), and ``/api/fleet`` with them (issue 32: 40,933
rows after a 40,000-id flood, ``/api/fleet`` 22 MB, never forgotten)."""

import warnings

from test_dashboard_app import TOKEN, FakeControl, heading_batch

from services.dashboard.app import create_app
from services.dashboard.state import FORGET_AFTER_S, MAX_ROWS, FleetState

with warnings.catch_warnings():
    warnings.filterwarnings("ignore", message=".*httpx.*")
    from starlette.testclient import TestClient


def test_a_flood_of_40000_ids_leaves_the_rows_bounded_and_the_real_device_shown():
    now = [0.0]
    state = FleetState(None, clock=lambda: now[0])
    assert MAX_ROWS <= 10_000 and 60 <= FORGET_AFTER_S <= 3600  # the defaults: a fleet's size, minutes of silence
    state.on_heading(heading_batch("real-1"))
    for i in range(40_000):
        state.on_alive(f"flood-{i:05d}", True)
        if i % 1000 == 0:  # the real device keeps sending through the flood
            now[0] += 0.1
            state.on_heading(heading_batch("real-1", seq=i))
    assert len(state.rows) == MAX_ROWS and state.forgotten == 40_001 - MAX_ROWS
    assert state.knows("real-1") and not state.knows("flood-00000") and state.knows("flood-39999")
    client = TestClient(create_app(state, FakeControl(), TOKEN, view_needs_token=False), base_url="http://127.0.0.1")
    fleet = client.get("/api/fleet")
    assert fleet.status_code == 200 and len(fleet.json()["rows"]) == MAX_ROWS
    assert len(fleet.content) < 8 * 1024 * 1024  # 22 MB before, for 40,933 rows
    assert client.get("/api/stream", params={"device": "flood-00000"}).status_code == 404  # forgotten: not streamed
    # the flood's tokens go; ten minutes later only the device that kept sending is left
    for i in range(40_000 - MAX_ROWS, 40_000):
        state.on_alive(f"flood-{i:05d}", False)
    now[0] += FORGET_AFTER_S / 2
    state.on_heading(heading_batch("real-1", seq=99_999))
    assert state.forget_silent() == 0
    now[0] += FORGET_AFTER_S / 2 + 1
    assert state.forget_silent() == MAX_ROWS - 1
    assert list(state.rows) == ["real-1"] and client.get("/api/fleet").json()["rows"][0]["device"] == "real-1"


def test_a_silent_row_is_forgotten_unless_its_token_lives_and_the_page_is_told():
    now = [0.0]
    state = FleetState(None, clock=lambda: now[0], forget_after_s=60.0)
    state.on_heading(heading_batch("gone-1"))
    state.on_heading(heading_batch("edge-up"))
    state.on_alive("edge-up", True)  # its edge (and token) lives on though its headings stopped
    seen = state.fleet(-1)
    assert seen["full"] and {r["device"] for r in seen["rows"]} == {"gone-1", "edge-up"}
    now[0] = 59.0
    assert state.forget_silent() == 0
    now[0] = 61.0
    assert state.forget_silent() == 1 and list(state.rows) == ["edge-up"]
    later = state.fleet(seen["version"])  # a page that had both rows is told to drop the forgotten one
    assert later["gone"] == ["gone-1"] and later["rows"] == [] and not later["full"]
    state.on_heading(heading_batch("gone-1"))  # heard of again: a row again
    assert state.knows("gone-1")
    again = state.fleet(later["version"])
    assert [r["device"] for r in again["rows"]] == ["gone-1"] and again["gone"] == []


def test_a_page_further_behind_than_the_forgotten_kept_gets_every_row():
    state = FleetState(None, max_rows=10)
    state.on_heading(heading_batch("keep"))
    start = state.fleet(-1)["version"]
    for i in range(6000):  # more forgotten than remembered for the streams
        state.on_alive(f"x{i}", False)
        state.on_heading(heading_batch("keep"))
    behind = state.fleet(start)
    assert behind["full"] and len(behind["rows"]) == 10 and behind["gone"] == []
    recent = state.fleet(state.version - 5)
    assert not recent["full"] and recent["gone"]
