"""The pipeline bench's in-process line: the compass's decode -> step -> encode on the load's own messages, every
one decoded and headed (no drop: the figures are of real work), each device's batches continuing one another."""

from magnet import wire
from services.bench import compass_drain


def test_the_in_process_drains_are_the_loads_messages_all_decoded_and_fused():
    items = compass_drain._messages(3, 10, True, 500.0, 2)
    assert [key for key, _ in items] == [wire.key("magnet", f"b-00{d}", wire.Kind.RAW) for d in range(3)] * 2
    core = compass_drain._core(3)
    columns = core.decode(items, "magnet")
    out = core.step(columns, int(columns.t_ns[-1]))
    assert not core.drops.counts and len(columns.devices) == 6
    assert out.quat_wxyz is not None and core.filters.devices.get("b-000").restarts == 1  # one start, then continued
    assert len(core.encode(columns, out)) == 6
    cost = compass_drain.drain_cost(devices=3, batch=10, gyro=False, rounds=1, repeats=1)
    assert cost.decode_us > 0 and cost.step_us > 0 and cost.encode_us > 0 and cost.batch == 10
    assert "us a batch" in cost.line(3, False)
