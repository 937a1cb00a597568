"""``CalibratorCore`` on a store in memory (``memory_store.MemoryStore``, the store protocol) and clocks the test
holds: its decisions (collect, fit, store, publish; sessions, rollback; standing by and taking over; status) with no
network, no database and no clock of its own."""

from __future__ import annotations

import numpy as np
import pytest
from memory_store import MemoryStore, check_store_contract, new_signer, record_of

from magnet import signing, wire
from magnet.calibrator import CalibratorCore
from magnet.shard import Shard
from magnet.simulator import SensorErrors, SimulatorConfig, simulate
from services.calibrator.settings import CalibratorSettings

HARD = np.array([30.0, -12.0, 8.0])
SOFT = np.array([[1.1, 0.04, 0.0], [0.04, 0.9, 0.02], [0.0, 0.02, 1.0]])
NOW_NS = 1_700_000_000_000_000_000


class Clocks:
    """A monotonic clock that moves 10 ms a reading, and a wall clock that says what the test sets."""

    def __init__(self) -> None:
        self.t_s = 0.0
        self.t_ns = NOW_NS

    def monotonic(self) -> float:
        self.t_s += 0.01
        return self.t_s

    def wall_ns(self) -> int:
        return self.t_ns


class Published(list[tuple[wire.Kind, str, bytes]]):
    def __call__(self, kind: wire.Kind, device: str, payload: bytes) -> None:
        self.append((kind, device, payload))

    def of(self, kind: wire.Kind) -> list[bytes]:
        return [payload for k, _, payload in self if k is kind]


def _run(count: int = 3000, hard: np.ndarray = HARD, seed: int = 0):
    errors = SensorErrors(hard_iron_ut=hard, soft_iron=SOFT, noise_ut=0.3)
    return simulate(SimulatorConfig(count=count, seed=seed, errors=errors))


def _feed(core: CalibratorCore, run, device: str = "d", batch: int = 50) -> None:
    for seq, start in enumerate(range(0, len(run.t_s), batch)):
        part = slice(start, start + batch)
        t_ns = np.arange(start, start + len(run.t_s[part]))
        raw = wire.RawBatch(device, seq, "sim", t_ns, run.mag_ut[part], run.acc_ms2[part])
        core.on_raw(f"magnet/{device}/raw", wire.encode_raw(raw), "magnet")


def _core(store: MemoryStore, clocks: Clocks, published: Published, **kwargs) -> CalibratorCore:
    signer = kwargs.pop("signer", None)
    shard = kwargs.pop("shard", Shard(0, 1))
    return CalibratorCore(
        store, CalibratorSettings(**kwargs), published, clocks.monotonic, clocks.wall_ns, signer, shard=shard
    )


@pytest.fixture
def parts() -> tuple[MemoryStore, Clocks, Published]:
    return MemoryStore(), Clocks(), Published()


def test_the_memory_store_keeps_the_store_contract():
    check_store_contract(MemoryStore())


def test_an_automatic_fit_is_stored_with_its_change_published_and_its_collection_ended(parts):
    store, clocks, published = parts
    core = _core(store, clocks, published)
    _feed(core, _run())
    [(record, change)] = store.history_changes("d")
    assert record.version == 1 and record.created_ns == NOW_NS, "numbered by the store, stamped by the given clock"
    np.testing.assert_allclose(record.calibration.offset, HARD, atol=1.0)
    assert change == {"action": "auto", "by": "", "at_ns": NOW_NS, "from_id": None}
    assert [wire.decode_calibration(p).id for p in published.of(wire.Kind.CALIBRATION)] == [record.id]
    assert wire.decode_progress(published.of(wire.Kind.PROGRESS)[-1])["state"] == "calibrated"
    assert core.records.in_force["d"].to_record() == record.to_record() and "d" not in core.collections
    status = core.status("c").to_dict()
    assert (status["stored"], status["accepted"], status["devices"]["calibrated"]) == (1, 1, 1)
    assert status["fits"] >= 1 and status["received_batches"] == 3000 // 50


def test_sessions_and_rollback_go_through_the_store_as_changes_the_record_in_force_moving_only_on_success(parts):
    store, clocks, published = parts
    core = _core(store, clocks, published, auto=False)
    assert not core.session("d", "start", None)["ok"], "an unknown device"
    _feed(core, _run(count=50))
    assert core.session("d", "start", "ellipsoid", by="ann@lab")["state"] == "session"
    _feed(core, _run())
    assert store.history("d") == [], "a session stores only on commit"
    first = core.session("d", "commit", None, by="bob@lab")
    assert first["ok"] and first["calibration"]["version"] == 1
    core.session("d", "start", "ellipsoid")
    _feed(core, _run(hard=HARD + 5.0, seed=1))
    clocks.t_ns += 1_000
    second = core.session("d", "commit", None)
    assert second["ok"] and second["calibration"]["version"] == 2
    back = core.rollback("d", None, "carol@lab")
    assert back["ok"] and back["calibration"]["version"] == 3, back["message"]
    rows = store.history_changes("d")
    assert [r.calibration.content_id for r, _ in rows] == [
        rows[2][0].calibration.content_id,
        rows[1][0].calibration.content_id,
        rows[2][0].calibration.content_id,
    ], "the rollback put the first calibration back in force as a new version"
    assert rows[0][1] == {
        "action": "rollback",
        "by": "carol@lab",
        "to_id": rows[2][0].id,
        "at_ns": NOW_NS + 1_000,
        "from_id": rows[1][0].id,
    }
    assert rows[2][1] is not None and (rows[2][1]["action"], rows[2][1]["by"]) == ("session", "bob@lab")
    refused = core.rollback("d", rows[0][0].id, None)
    assert not refused["ok"] and "already in force" in refused["message"]
    assert len(store.history("d")) == 3 and core.records.in_force["d"].id == rows[0][0].id


def test_a_store_that_fails_changes_nothing_and_collection_goes_on(parts):
    store, clocks, published = parts
    core = _core(store, clocks, published)
    store.failing = OSError("disk full: free space")
    _feed(core, _run())
    assert core.records.in_force == {} and store.rows == []
    assert core.drops.counts["store:write-failed"] >= 1 and core.state("d").value == "collecting"
    assert published.of(wire.Kind.CALIBRATION) == []
    core.session("d", "start", "ellipsoid")
    _feed(core, _run())
    refused = core.session("d", "commit", None)
    assert not refused["ok"] and "the calibration in force stays: disk full" in refused["message"]
    rollback = core.rollback("d", None, None)
    assert not rollback["ok"] and "disk full" in rollback["message"]
    store.failing = None
    assert core.session("d", "commit", None)["ok"], "the session's samples were kept for another try"


def test_standing_by_it_collects_nothing_and_taking_over_it_serves_what_another_stored(parts):
    store, clocks, published = parts
    core = _core(store, clocks, published, auto=False)
    _feed(core, _run(count=50))
    core.session("d", "start", "ellipsoid")
    core.stand_by()
    assert core.state("d").value == "idle", "the session was dropped"
    _feed(core, _run(count=100), device="e")
    assert core.status("c").counters.received_batches == 1 and core.status("c").lease == "standby"
    store.append("e", lambda version: record_of("e", version), {"action": "auto", "by": ""})  # the active one stored
    core.take_over()
    assert core.records.in_force["e"].version == 1 and core.status("c").counters.takeovers == 1
    assert [wire.decode_calibration(p).device for p in published.of(wire.Kind.CALIBRATION)] == ["e"]


def test_it_serves_only_its_shard_and_signs_what_it_makes(parts):
    store, clocks, published = parts
    shard = Shard(0, 2)
    mine, theirs = (next(f"dev{i}" for i in range(100) if shard.owns(f"dev{i}") is want) for want in (True, False))
    signer = new_signer()
    core = _core(store, clocks, published, shard=shard, signer=signer)
    _feed(core, _run(), device=theirs)
    assert core.status("c").counters.received_batches == 0 and store.rows == []
    _feed(core, _run(), device=mine)
    record = store.latest(mine)
    assert record is not None and record.sig
    signing.TrustedKeys([signer.private_key.public_key()]).verify(record.to_record())
