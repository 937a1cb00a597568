"""The compass's answers pinned on the pipeline bench's own drains (issue 28: the cost cuts must not move them).
``CompassCore.step``'s outputs (headings, pitch, roll, field, flags, true headings, dips, quaternions, sigmas) and the
heading payloads of 12 devices over 1.6 s (800 samples each at 500 Hz with gyroscopes, past three of the turn gate's
0.5 s blocks), in drains of 5 and of 12 messages, with and without gyroscopes.

Two checks. Everywhere: each output's weighted sum (fixed pseudo-random weights) against the pinned one within a
relative 1e-9 and its NaN count exactly, so a cost cut that moves any answer by more than the last bits fails on any
machine. On the platform the bits were pinned on (numpy's version, the CPU features numpy dispatches to, vqf's
version): the sha256 of every output and payload, to the bit. numpy's transcendental functions (``arctan2``, ``sin``)
take other code paths on other CPUs and versions, which moves last bits and nothing else.

A cut of the compass's cost leaves both as they are. A change that means to change the answers (new maths, new
flags, another wire format) changes them: check that the new answers are the intended ones, then replace the pinned
figures here with the ones the failure prints, saying why in the commit."""

import hashlib
from importlib import metadata

import numpy as np
import pytest
from numpy._core._multiarray_umath import __cpu_dispatch__, __cpu_features__

from services.bench import compass_drain

DEVICES, ROUNDS = 12, 8
NAMES = ("heading_deg", "pitch_deg", "roll_deg", "field_ut", "flags", "true_heading_deg", "dip_deg", "quat_wxyz",
         "heading_sigma_deg", "tilt_sigma_deg")  # fmt: skip
#: where the digests were made: numpy's version, the CPU features its dispatch uses, vqf's version
PLATFORM = ("2.4.6", ("X86_V3", "X86_V4", "AVX512_ICL", "AVX512_SPR"), "2.1.2")
PINNED = {
    (False, 5): "e3a56f04724bdd02929483470ffb96d87b885229d39e8d2f0a1bf2073490b150",
    (False, 12): "d7eb099e2f94b2f4c0008da8dcd99a33f31b779aa06171cca63de392c4d10c23",
    (True, 5): "8dbf179a72994567aa9ac2de76ca4c512ae028c134d1268825956365259761d5",
    (True, 12): "b0758b4685a10829b2bee321b22b7e692ae5ed7bbec2d61623ca78f4d38fb73a",
}
#: each output's (sum of w x, sum of w |x|, count not finite), ``_weighted``
SUMS = {
    (False, 5): {
        "heading_deg": (1921253.0418776106, 1921253.0418776106, 0),
        "pitch_deg": (20000.50752979156, 541835.1462734602, 0),
        "roll_deg": (74125.07965512342, 796826.7899959988, 0),
        "field_ut": (-229981.72831333397, 1051074.812457567, 0),
        "flags": (9598.163878229545, 9598.163878229545, 0),
        "true_heading_deg": (1921253.0418776106, 1921253.0418776106, 0),
        "dip_deg": (393006.1983024914, 453315.6450276004, 0),
        "heading_sigma_deg": (116016.20039292784, 116016.20039292784, 0),
        "tilt_sigma_deg": (1198.5464998249647, 1198.5464998249647, 0),
    },
    (False, 12): {
        "heading_deg": (1921253.0418776106, 1921253.0418776106, 0),
        "pitch_deg": (20000.50752979156, 541835.1462734602, 0),
        "roll_deg": (74125.07965512342, 796826.7899959988, 0),
        "field_ut": (-229981.72831333397, 1051074.812457567, 0),
        "flags": (9598.163878229545, 9598.163878229545, 0),
        "true_heading_deg": (1921253.0418776106, 1921253.0418776106, 0),
        "dip_deg": (393006.1983024914, 453315.6450276004, 0),
        "heading_sigma_deg": (116016.20039292784, 116016.20039292784, 0),
        "tilt_sigma_deg": (1198.5464998249647, 1198.5464998249647, 0),
    },
    (True, 5): {
        "heading_deg": (2136966.517621816, 2136966.517621816, 0),
        "pitch_deg": (24191.56385379855, 292019.28456997545, 0),
        "roll_deg": (70512.16352411272, 820942.0264247227, 0),
        "field_ut": (-229981.72831333397, 1051074.812457567, 0),
        "flags": (201561.4414428205, 201561.4414428205, 0),
        "true_heading_deg": (2136966.517621816, 2136966.517621816, 0),
        "dip_deg": (249366.37164595787, 336595.98144078016, 0),
        "quat_wxyz": (2952.7671109875955, 16230.405419218165, 0),
        "heading_sigma_deg": (4159.06809493329, 4159.06809493329, 0),
        "tilt_sigma_deg": (10256.011400130825, 10256.011400130825, 0),
    },
    (True, 12): {
        "heading_deg": (2136966.517621816, 2136966.517621816, 0),
        "pitch_deg": (24191.56385379855, 292019.28456997545, 0),
        "roll_deg": (70512.16352411272, 820942.0264247227, 0),
        "field_ut": (-229981.72831333397, 1051074.812457567, 0),
        "flags": (201561.4414428205, 201561.4414428205, 0),
        "true_heading_deg": (2136966.517621816, 2136966.517621816, 0),
        "dip_deg": (249366.37164595787, 336595.98144078016, 0),
        "quat_wxyz": (2952.7671109875955, 16230.405419218165, 0),
        "heading_sigma_deg": (4159.068101751678, 4159.068101751678, 0),
        "tilt_sigma_deg": (10256.012106739501, 10256.012106739501, 0),
    },
}


def _platform() -> tuple[str, tuple[str, ...], str]:
    dispatched = tuple(name for name in __cpu_dispatch__ if __cpu_features__.get(name))
    return np.__version__, dispatched, metadata.version("vqf")


def _run(gyro: bool, drain_messages: int) -> tuple[str, dict[str, tuple[float, float, int]]]:
    """The digest of every output and payload, and each output's figures (``_weighted``) over all drains."""
    core = compass_drain._core(DEVICES)
    items = compass_drain._messages(DEVICES, 100, gyro, 500.0 if gyro else 1000.0, ROUNDS)
    digest = hashlib.sha256()
    parts: dict[str, list[np.ndarray]] = {name: [] for name in NAMES}
    for start in range(0, len(items), drain_messages):
        columns = core.decode(items[start : start + drain_messages], "magnet")
        out = core.step(columns, int(columns.t_ns[-1]))
        h = out.headings
        arrays = (h.heading_deg, h.pitch_deg, h.roll_deg, h.field_ut, h.flags, out.true_heading_deg, out.dip_deg,
                  out.quat_wxyz, out.heading_sigma_deg, out.tilt_sigma_deg)  # fmt: skip
        for name, array in zip(NAMES, arrays, strict=True):
            digest.update(b"-" if array is None else np.ascontiguousarray(array).tobytes())
            if array is not None:
                parts[name].append(np.asarray(array, dtype=np.float64).ravel())
        for payload in core.encode(columns, out):
            digest.update(payload)
        digest.update(repr((out.calibration_ids, out.declinations)).encode())
    assert not core.drops.counts
    return digest.hexdigest(), {name: _weighted(parts[name]) for name in NAMES if parts[name]}


def _weighted(parts: list[np.ndarray]) -> tuple[float, float, int]:
    """(sum of w x, sum of w |x|, count of x not finite) over the finite x, weights w fixed in 0.5-1.5."""
    values = np.concatenate(parts)
    weights = np.random.default_rng(28).uniform(0.5, 1.5, values.size)
    finite = np.where(np.isfinite(values), values, 0.0)
    return float(finite @ weights), float(np.abs(finite) @ weights), int(values.size - np.isfinite(values).sum())


@pytest.fixture(scope="module", params=sorted(PINNED), ids=lambda key: f"gyro={key[0]}-drain={key[1]}")
def run(request):
    return request.param, _run(*request.param)


def test_every_answer_is_as_pinned_within_the_last_bits(run):
    key, (_, sums) = run
    for name, (total, scale, not_finite) in SUMS[key].items():
        got = sums.get(name)
        assert got is not None and got[2] == not_finite and abs(got[0] - total) <= 1e-9 * scale, (
            f"the compass's {name} changed ({'gyroscopes' if key[0] else 'no gyroscopes'}, drains of {key[1]}): "
            f"{got} against {(total, scale, not_finite)}; a cost cut must leave it; an intended change of the answers "
            "replaces the pinned figures (see the module docstring)"
        )
    assert sums.keys() == SUMS[key].keys()


def test_the_answers_are_as_pinned_to_the_bit_on_the_platform_they_were_pinned_on(run):
    key, (digest, _) = run
    if _platform() != PLATFORM:
        pytest.skip(f"pinned on numpy, CPU dispatch, vqf {PLATFORM}; this is {_platform()} (the weighted sums check)")
    assert digest == PINNED[key], (
        f"the compass's outputs or payloads changed ({'gyroscopes' if key[0] else 'no gyroscopes'}, drains of "
        f"{key[1]}): a cost cut must leave them to the bit; an intended change of the answers replaces the pinned "
        f"digest with {digest!r} (see the module docstring)"
    )
