"""The fleet events of the dashboard's streams (``services.dashboard.events``): made once a tick by one producer off
the event loop, only looked up by the streams, bounded, and a stream that cannot keep up closed with its reason
(issue 32: a 5-minute soak found the loop stuck for minutes re-encoding every row, 6 MB, for each new stream, 5,879
of 8,000 streams unanswered and the dashboard at 781 MB)."""

import asyncio
import json
import time

import pytest
from test_dashboard_app import TOKEN, FakeControl, heading_batch

from services.dashboard import events as events_module
from services.dashboard.app import create_app
from services.dashboard.events import (
    KEPT_TICKS,
    RESYNCS_TO_CLOSE,
    FleetEvents,
    Reader,
    encode_fleet,
    fleet_body,
    fleet_event,
)
from services.dashboard.state import FleetState


def data_of(event: bytes) -> dict:
    name, data = event.decode().split("\n", 1)
    assert name == "event: fleet" and event.endswith(b"\n\n")
    return json.loads(data[len("data: ") :])


def devices_in(event: bytes) -> list[str]:
    return [row["device"] for row in data_of(event)["rows"]]


def test_a_tick_is_made_once_whatever_the_number_of_streams_and_taking_encodes_nothing():
    state = FleetState(None)
    state.on_heading(heading_batch("a"))
    events = FleetEvents(state, 0.25)
    readers = [Reader() for _ in range(100)]
    assert all(events.take(r) == ([], None) for r in readers) and events.wants_full  # new: every row, next tick
    events.make()  # the first tick: every row, once for the hundred
    assert events.made == 1
    firsts = [events.take(r)[0] for r in readers]
    assert all(len(f) == 1 and f[0] is firsts[0][0] for f in firsts)  # the same bytes object for every stream
    assert devices_in(firsts[0][0]) == ["a"] and data_of(firsts[0][0])["full"] is True
    state.on_heading(heading_batch("b"))
    events.make()
    links = [events.take(r)[0] for r in readers]
    assert all(len(x) == 1 and x[0] is links[0][0] for x in links) and devices_in(links[0][0]) == ["b"]
    assert all(events.take(r) == ([], None) for r in readers)  # woke twice in one tick: nothing new
    late = events.take(Reader())  # a new stream: the full made before and the link since, nothing made again
    assert late == ([firsts[0][0], links[0][0]], None) and events.made == 2 and events.resyncs == 0
    for i in range(KEPT_TICKS):  # the full leaves the chain; a new stream then waits a tick for a new one
        state.on_heading(heading_batch(f"c{i}"))
        events.make()
    assert events.full is None and events.take(Reader()) == ([], None) and events.made == 2 + KEPT_TICKS
    events.make()
    assert events.made == 4 + KEPT_TICKS  # the tick's link and every row


def test_a_stream_that_slept_through_ticks_gets_the_links_it_missed_in_order():
    state = FleetState(None)
    state.on_heading(heading_batch("a"))
    events = FleetEvents(state, 0.25)
    reader = Reader()
    events.take(reader)
    events.make()
    assert devices_in(events.take(reader)[0][0]) == ["a"]
    for device in ("c", "d"):
        state.on_heading(heading_batch(device))
        events.make()
    late, closing = events.take(reader)
    assert closing is None and [devices_in(t) for t in late] == [["c"], ["d"]]
    assert reader.version == state.version


def test_a_stream_further_behind_than_the_chain_gets_every_row_again_then_is_closed_saying_why():
    state = FleetState(None)
    events = FleetEvents(state, 0.25)
    reader = Reader()
    events.take(reader)
    state.on_heading(heading_batch("a"))
    events.make()
    events.take(reader)
    for attempt in range(1, RESYNCS_TO_CLOSE + 1):
        for i in range(KEPT_TICKS + 1):  # more ticks than kept: its backlog is gone
            state.on_heading(heading_batch(f"x{i}"))
            events.make()
        taken, closing = events.take(reader)
        if attempt == RESYNCS_TO_CLOSE:
            assert taken == [] and "fell behind" in closing and "reads too slowly" in closing and events.closed == 1
            break
        assert (taken, closing) == ([], None)  # the last full left the chain: every row made at the next tick
        events.make()
        taken, closing = events.take(reader)
        assert closing is None and data_of(taken[0])["full"] is True  # the page drops what it holds
        assert len(data_of(taken[0])["rows"]) == KEPT_TICKS + 2 and reader.version == state.version
        assert events.resyncs == attempt
    fresh = Reader()  # a stream that keeps up is never closed
    events.take(fresh)
    events.make()
    for i in range(3 * KEPT_TICKS):
        state.on_heading(heading_batch(f"y{i % 3}"))
        events.make()
        assert events.take(fresh)[1] is None and fresh.resyncs == 0


def test_the_chain_is_kept_within_its_bytes(monkeypatch):
    monkeypatch.setattr(events_module, "KEPT_BYTES", 200_000)
    state = FleetState(None)
    events = FleetEvents(state, 0.25)
    for tick in range(KEPT_TICKS):
        for i in range(300):  # every row changed each tick: links of about 190 kB
            state.on_heading(heading_batch(f"d{i:03d}", seq=tick))
        events.make()
        assert len(events.chain) == 1 or sum(len(link.text) for link in events.chain) <= 200_000
    assert len(events.chain) < KEPT_TICKS
    assert all(a.version == b.base for a, b in zip(events.chain, events.chain[1:]))  # a chain: no version skipped


@pytest.mark.parametrize("count", [0, 1, 450])
def test_rows_encoded_in_chunks_are_the_json_of_one_dumps(count):
    state = FleetState(None)
    for i in range(count):
        state.on_heading(heading_batch(f"d{i:03d}"))
    fleet, summary = state.fleet(-1), state.summary()
    assert data_of(encode_fleet(fleet, summary)) == json.loads(json.dumps(fleet | {"summary": summary}))
    assert json.loads(fleet_body(state)) == json.loads(json.dumps(fleet | {"summary": summary}))
    version, event = fleet_event(state, -1)
    assert version == fleet["version"] and event == encode_fleet(fleet, summary)
    if count:
        state.on_heading(heading_batch("d000", seq=99))  # one row changed: only it
        assert devices_in(fleet_event(state, version)[1]) == ["d000"]


def test_a_burst_of_new_streams_costs_one_encoding_even_when_encoding_takes_longer_than_a_tick():
    """The soak's failure: encoding every row took longer than a tick, so each new stream found the tick's full
    event out of date and encoded it again, on the loop (one per stream: here 60)."""
    state = FleetState(None)
    for i in range(60):  # a first event of about 40 kB: one piece
        state.on_heading(heading_batch(f"d{i:03d}"))
    fleet_chunks = state.fleet_chunks

    def slow_chunks(*args):
        time.sleep(0.03)  # longer than the 0.01 s tick, as 10,000 rows on a loaded machine
        return fleet_chunks(*args)

    state.fleet = lambda since: (time.sleep(0.03), FleetState.fleet(state, since))[1]  # the same, for the old code
    state.fleet_chunks = slow_chunks
    app = create_app(state, FakeControl(), TOKEN, interval_s=0.01)
    dashboard = app.state.dashboard

    async def first_event():
        stream = dashboard._events(None)
        async for piece in stream:
            first = bytes(piece)
            await stream.aclose()
            return first
        return b""

    async def burst():
        beats = 0

        async def heartbeat():  # the loop is not held by the encoding (it runs in the producer's thread)
            nonlocal beats
            while True:
                beats += 1
                await asyncio.sleep(0)

        beating = asyncio.ensure_future(heartbeat())
        firsts = [await first_event() for _ in range(60)]  # new streams one after another, as pages reconnecting
        beating.cancel()
        return firsts, beats

    firsts, beats = asyncio.run(burst())
    assert all(f.startswith(b"event: fleet") and len(data_of(f)["rows"]) == 60 for f in firsts)
    assert dashboard.events.made <= 20, dashboard.events.made  # before: at least one full encoding per stream
    assert beats > 60 and dashboard.streams == 0 and dashboard.events.readers == 0
    dashboard.events.close()
