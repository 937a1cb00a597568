"""A fuzz campaign over every decoder and file reader: arbitrary bytes, and genuine messages, records and files with
fields replaced, removed or added by arbitrary values, give the documented error (``WireError`` on the wire,
``ValueError`` for records and files, an error reply for a query) or a good result, never another exception.

Each property runs a bounded number of examples (``FUZZ``: 40; ``FUZZ_ALL``: 60 shared by the seven message decoders)
derived from the test's name (``derandomize``), so the suite is deterministic and takes about 2 s of CPU; raise
``max_examples`` and drop ``derandomize`` locally to search further. Every kind of message is one ``TEMPLATES``
entry and one ``DECODERS`` entry; every file reader of ``services.common.inputs.FORMATS`` is fuzzed by suffix."""

from __future__ import annotations

import contextlib
import json
import struct
import tempfile
from pathlib import Path

import msgpack
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from magnet import wire
from magnet.drift import Alert, AlertKind, alert_from_message
from magnet.drift.alerts import ALERT_LIMITS
from magnet.model import Calibration
from services.calibrator import queries
from services.calibrator.service import Calibrator, CalibratorSettings
from services.calibrator.store import CalibrationStore
from services.common import jsonio
from services.common.inputs import FORMATS, csvio, read_input

FUZZ = settings(
    max_examples=40, deadline=2000, derandomize=True, suppress_health_check=[HealthCheck.too_slow], database=None
)
#: the decoders share their examples (each example picks one): a few hundred in all, generation being the cost
FUZZ_ALL = settings(FUZZ, max_examples=60)

SCALARS = (
    st.none()
    | st.booleans()
    | st.integers(-(2**63), 2**64 - 1)
    | st.floats()
    | st.text(max_size=8)
    | st.binary(max_size=24)
)
#: any msgpack value: scalars, lists and maps of them, a few levels deep
VALUES = st.recursive(
    SCALARS,
    lambda inner: st.lists(inner, max_size=5) | st.dictionaries(st.text(max_size=8), inner, max_size=5),
    max_leaves=8,
)
#: any JSON value
JSON_VALUES = st.recursive(
    st.none() | st.booleans() | st.integers() | st.floats(allow_nan=False) | st.text(max_size=12),
    lambda inner: st.lists(inner, max_size=5) | st.dictionaries(st.text(max_size=8), inner, max_size=5),
    max_leaves=8,
)
DELETE = object()


def _unpacked(payload):
    return msgpack.unpackb(payload, raw=False)


def _templates():
    """Genuine messages of every kind, as maps."""
    n = 4
    vec = np.arange(n * 3, dtype=float).reshape(n, 3) + 1.0
    truth = {name: np.zeros(n) for name in wire.TRUTH_FIELDS}
    raw = wire.RawBatch("dev", 3, "sim", np.arange(n), vec, vec, truth, vec / 10, vel_ned_ms=vec)
    zeros = np.zeros(n)
    quat = np.tile([1.0, 0.0, 0.0, 0.0], (n, 1))
    heading = wire.HeadingBatch("dev", 3, np.arange(n), zeros, zeros, zeros, zeros, vec, 2.0, "abc", zeros, quat)
    calibration = Calibration("ellipsoid", [1.0, 2.0, 3.0], np.diag([1.0, 1.1, 0.9]), field_strength=50.0)
    return {
        "raw1": _unpacked(wire.encode_raw(raw, version=1)),
        "raw2": _unpacked(wire.encode_raw(raw, version=2)),
        "heading1": _unpacked(wire.encode_heading(heading, version=1)),
        "heading2": _unpacked(wire.encode_heading(heading, version=2)),
        "calibration": _unpacked(wire.encode_calibration("dev", calibration, 5)),
        "progress": _unpacked(wire.encode_progress("dev", {"state": "collecting", "t_ns": 1, "missing": ["up"]})),
        "alert": Alert("dev", AlertKind.DIP, 1, 60.0, 62.0, "look", False).to_message(),
    }


TEMPLATES = _templates()


@st.composite
def mutated(draw, template):
    """``template`` with 1-3 fields (or fields of its nested maps and lists) replaced, removed or added."""
    message = _unpacked(msgpack.packb(template, use_bin_type=True))  # a deep copy to change
    for _ in range(draw(st.integers(1, 3))):
        target = message
        key = draw(st.sampled_from([*message, "extra"]))
        inner = message.get(key)
        if isinstance(inner, dict) and inner and draw(st.booleans()):
            target, key = inner, draw(st.sampled_from([*inner, "extra"]))
        elif isinstance(inner, list) and inner and draw(st.booleans()):
            target, key = inner, draw(st.integers(0, len(inner) - 1))
        value = draw(VALUES | st.just(DELETE))
        if value is DELETE:
            if isinstance(target, dict):
                target.pop(key, None)
        else:
            target[key] = value
    return msgpack.packb(message, use_bin_type=True)


def _alert(payload):
    message = wire.unpack(payload, ALERT_LIMITS)
    wire.message_device(message)
    return alert_from_message(message)


#: decoder -> the template of the messages it reads, and the error it may raise
DECODERS = {
    "raw1": (wire.decode_raw, wire.WireError),
    "raw2": (wire.decode_raw, wire.WireError),
    "heading1": (wire.decode_heading, wire.WireError),
    "heading2": (wire.decode_heading, wire.WireError),
    "calibration": (wire.decode_calibration, wire.WireError),
    "progress": (wire.decode_progress, wire.WireError),
    "alert": (_alert, ValueError),
}


def _decodes_or_refuses(decode, error, payload):
    with contextlib.suppress(error):
        decode(payload)


@FUZZ_ALL
@given(st.data())
def test_arbitrary_bytes_give_the_documented_error(data):
    decode, error = DECODERS[data.draw(st.sampled_from(sorted(DECODERS)))]
    payload = data.draw(st.binary(max_size=200) | VALUES.map(lambda v: msgpack.packb(v, use_bin_type=True)))
    _decodes_or_refuses(decode, error, payload)


@pytest.mark.parametrize("kind", sorted(DECODERS))
def test_the_templates_are_good(kind):
    decode, _ = DECODERS[kind]
    decode(msgpack.packb(TEMPLATES[kind], use_bin_type=True))


@FUZZ_ALL
@given(st.data())
def test_genuine_messages_with_wrong_fields_give_the_documented_error(data):
    kind = data.draw(st.sampled_from(sorted(DECODERS)))
    decode, error = DECODERS[kind]
    _decodes_or_refuses(decode, error, data.draw(mutated(TEMPLATES[kind])))


@settings(FUZZ, max_examples=40)
@given(st.lists(mutated(TEMPLATES["raw1"]) | mutated(TEMPLATES["raw2"]) | st.binary(max_size=64), max_size=4))
def test_the_raw_decoder_of_many_never_raises_and_names_each_refusal(payloads):
    columns, errors = wire.decode_raw_many(payloads)
    assert len(columns.devices) + len(errors) == len(payloads)
    assert all(isinstance(e, wire.WireError) and e.__traceback__ is None for _, e in errors)


@FUZZ
@given(st.dictionaries(st.sampled_from([*TEMPLATES["calibration"], "quality"]), JSON_VALUES, max_size=4))
def test_a_calibration_record_from_json_gives_a_value_error(changes):
    record = {**TEMPLATES["calibration"], **changes}
    with contextlib.suppress(ValueError):
        Calibration.from_dict(json.loads(json.dumps(record)))
    with contextlib.suppress(wire.WireError):
        wire.calibration_from_record(record)


class Query:
    """A query as a queryable sees it: its key, its parameters and the replies given."""

    def __init__(self, key, parameters):
        self.key_expr, self.parameters, self.replies = key, parameters, []

    def reply(self, key, payload):
        self.replies.append(("ok", key))

    def reply_err(self, payload):
        self.replies.append(("err", payload))


PARAMETER_TEXT = st.text(max_size=30) | st.sampled_from(["", "-1", "1e400", "9" * 30, "start", "rollback", "commit"])


def test_query_parameters_are_answered_or_refused():
    with tempfile.TemporaryDirectory() as tmp, CalibrationStore(Path(tmp) / "c.db") as store:
        calibrator = Calibrator(store, CalibratorSettings(), lambda *a: None, clock=lambda: 0.0, clock_ns=lambda: 1)

        @FUZZ
        @given(
            st.sampled_from([wire.Kind.CALIBRATE, wire.Kind.HISTORY, wire.Kind.CALIBRATION]),
            st.sampled_from(["dev", "x" * 200, "a b", "*"]),
            st.dictionaries(st.sampled_from(["action", "method", "to", "by", "limit"]), PARAMETER_TEXT, max_size=4),
        )
        def check(kind, device, parameters):
            with contextlib.suppress(ValueError):
                queries.history_limit(parameters.get("limit"))
            query = Query(f"magnet/{device}/{kind.value}", parameters)
            queries.ANSWERS[kind](query, calibrator, "magnet")
            assert all(kind_ in ("ok", "err") for kind_, _ in query.replies)

        check()


CSV_CELLS = st.text(alphabet=st.sampled_from('0123456789.-+eE,;"\n\t xyzmnai'), max_size=200)


def test_file_readers_give_a_value_error():
    with tempfile.TemporaryDirectory() as tmp:
        root = Path(tmp)

        @FUZZ
        @given(
            st.sampled_from(sorted(FORMATS)),
            st.binary(max_size=300) | CSV_CELLS.map(lambda t: ("mx,my,mz,ax,ay,az,gx,gy,gz,t_s\n" + t).encode()),
        )
        def check(suffix, content):
            path = root / f"f{suffix}"
            path.write_bytes(content)
            with contextlib.suppress(ValueError):
                read_input(path)
            with contextlib.suppress(ValueError):
                csvio.parse_samples(content.decode("utf-8", "replace"), "x")

        check()


def test_calibration_files_give_a_value_error():
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "cal.json"
        good = json.dumps(TEMPLATES["calibration"])

        @FUZZ
        @given(
            st.binary(max_size=300)
            | JSON_VALUES.map(lambda v: json.dumps(v).encode())
            | st.tuples(st.integers(0, len(good)), st.text(max_size=10)).map(
                lambda cut: (good[: cut[0]] + cut[1] + good[cut[0] :]).encode()
            )
        )
        def check(content):
            path.write_bytes(content)
            with contextlib.suppress(ValueError):
                Calibration.from_dict(jsonio.read_json(path))

        check()


def _recordings(root: Path) -> dict[str, bytes]:
    """Small genuine recordings of every binary kind, and the crafted bombs of ``test_log_bombs.py``."""
    from logfixtures import ARDUPILOT_LOG, simulated_run, write_tlog

    from tests.services.common import test_log_bombs as bombs

    write_tlog(root / "seed.tlog", simulated_run(count=600), count=100)
    sane = bombs.ulog_absurd_field().replace(struct.pack("<f", 3e38), struct.pack("<f", 0.4))
    return {
        ".ulg": sane,
        ".bin": ARDUPILOT_LOG.read_bytes()[:16384],
        ".tlog": (root / "seed.tlog").read_bytes(),
        ".mcap": bombs.mcap_bomb(16384, 16384),
        ".db3": bombs.small_db3(root).read_bytes(),
        ".ulg ": bombs.ulog_nested_bomb(),
        ".mcap ": bombs.mcap_bomb(1 << 20, 1 << 30),
    }


def test_recordings_with_bytes_changed_give_a_value_error():
    """Genuine recordings and crafted bombs with 1-8 bytes changed (or cut short): a table or a ValueError naming
    the file, within the memory ceiling of the bomb tests."""
    from tests.services.common.test_log_bombs import memory_ceiling

    with tempfile.TemporaryDirectory() as tmp:
        root = Path(tmp)
        seeds = _recordings(root)

        @settings(FUZZ, max_examples=30, deadline=None)
        @given(
            st.sampled_from(sorted(seeds)),
            st.lists(st.tuples(st.floats(0, 1, exclude_max=True), st.integers(0, 255)), min_size=1, max_size=8),
            st.none() | st.floats(0.05, 1),
        )
        def check(kind, changes, cut):
            content = bytearray(seeds[kind])
            for where, value in changes:
                content[int(where * len(content))] = value
            if cut is not None:
                content = content[: int(cut * len(content))]
            path = root / f"f{kind.strip()}"
            path.write_bytes(bytes(content))
            with memory_ceiling(), contextlib.suppress(ValueError):
                read_input(path)

        check()
