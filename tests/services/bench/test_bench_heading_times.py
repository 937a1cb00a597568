"""The pipeline bench's measurer reads each heading message's sample count and last time (``heading_times``) from
its ``t_ns`` entry alone; the same figures as the whole message decoded, in either wire version."""

import numpy as np

from magnet import wire
from magnet.wire.codec import BINARY_ARRAYS_VERSION, LISTS_VERSION
from services.bench import compass_drain
from services.bench.pipeline import heading_times


def test_heading_times_are_the_decoded_messages_count_and_last_time():
    core = compass_drain._core(4)
    items = compass_drain._messages(4, 100, True, 500.0, 2)
    columns = core.decode(items, "magnet")
    out = core.step(columns, int(columns.t_ns[-1]))
    h = out.headings
    for version in (BINARY_ARRAYS_VERSION, LISTS_VERSION):
        payloads = wire.encode_headings(
            columns, h.heading_deg, out.true_heading_deg, h.pitch_deg, h.roll_deg, h.field_ut, h.flags,
            out.declinations, out.calibration_ids, out.quat_wxyz, out.heading_sigma_deg, version=version,
        )  # fmt: skip
        for payload, batch in zip(payloads, columns.batches()):
            t_ns = wire.unpack(payload, wire.HEADING_LIMITS)["t_ns"]
            t_ns = np.frombuffer(t_ns["data"], "<i8") if isinstance(t_ns, dict) else np.asarray(t_ns)
            assert heading_times(payload) == (len(t_ns), int(t_ns[-1])) == (len(batch), int(batch.t_ns[-1]))
