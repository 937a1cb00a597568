"""Replay of a recording (magnet.edge.replay, ``magnet edge --replay``): pacing with a fake clock, checks, end to
end."""

from __future__ import annotations

import json

import numpy as np
import pytest
from helpers import replay_raw

from magnet.edge.replay import MAX_SLEEP_S, Recording, paced_slices
from services.cli import main
from services.edge.sources import read_recording


class FakeClock:
    def __init__(self) -> None:
        self.t = 100.0
        self.sleeps: list[float] = []

    def __call__(self) -> float:
        return self.t

    def sleep(self, seconds: float) -> None:
        self.sleeps.append(seconds)
        self.t += seconds


def recording(n: int = 25, rate_hz: float = 10.0, gyro: bool = True) -> Recording:
    rng = np.random.default_rng(0)
    return Recording(
        np.arange(n) / rate_hz,
        rng.normal(0, 30, (n, 3)),
        rng.normal(0, 3, (n, 3)),
        rng.normal(0, 1, (n, 3)) if gyro else None,
    )


def test_batches_are_released_at_the_recording_pace_scaled_by_speed():
    clock = FakeClock()
    released = [
        (part.start, part.stop, clock.t - 100.0)
        for part in paced_slices(recording(), 10, speed=2.0, clock=clock, sleep=clock.sleep)
    ]
    assert [(lo, hi) for lo, hi, _ in released] == [(0, 10), (10, 20), (20, 25)]
    # the last sample of each batch is due at t_s / speed: 0.9 / 2, 1.9 / 2, 2.4 / 2 seconds
    assert [t for _, _, t in released] == pytest.approx([0.45, 0.95, 1.2])


def test_a_gap_is_slept_in_short_steps_and_stop_ends_the_replay():
    clock = FakeClock()
    rec = Recording(np.array([0.0, 0.1, 30.0, 30.1]), np.ones((4, 3)))
    stop_at = 105.0
    parts = list(paced_slices(rec, 2, speed=1.0, clock=clock, sleep=clock.sleep, stop=lambda: clock.t >= stop_at))
    assert parts == [slice(0, 2)]
    assert max(clock.sleeps) <= MAX_SLEEP_S and stop_at <= clock.t < stop_at + MAX_SLEEP_S  # stop seen at once


def test_stamps_keep_the_recorded_intervals():
    rec = recording(5, rate_hz=100.0)
    assert rec.stamps_ns(1_000).tolist() == [1_000, 10_001_000, 20_001_000, 30_001_000, 40_001_000]


@pytest.mark.parametrize(
    "change,message",
    [
        (dict(t_s=np.array([0.0, 0.2, 0.1])), "go backwards at row 3"),
        (dict(t_s=np.array([0.0, np.nan, 0.2])), "must be finite"),
        (dict(mag_ut=np.array([[1.0, 2, 3], [np.inf, 0, 0], [1, 2, 3]])), "mag_ut row 2 is not finite"),
        (dict(gyr_rads=np.full((3, 3), 1e4)), "gyr_rads row 1"),
        (dict(acc_ms2=np.zeros((2, 3))), "acc_ms2 must have shape (3, 3)"),
    ],
)
def test_a_bad_recording_is_refused_with_the_row(change, message):
    fields = dict(t_s=np.array([0.0, 0.1, 0.2]), mag_ut=np.ones((3, 3)), acc_ms2=None, gyr_rads=None) | change
    with pytest.raises(ValueError, match=message.replace("(", r"\(").replace(")", r"\)")):
        Recording(**fields)


def write_csv(path, rec: Recording) -> None:
    columns = ["t_s", "mx", "my", "mz", "ax", "ay", "az"] + (["gx", "gy", "gz"] if rec.gyr_rads is not None else [])
    parts = [rec.t_s[:, None], rec.mag_ut, rec.acc_ms2] + ([rec.gyr_rads] if rec.gyr_rads is not None else [])
    rows = np.round(np.hstack(parts), 4)
    path.write_text(",".join(columns) + "\n" + "\n".join(",".join(f"{v:.4f}" for v in row) for row in rows) + "\n")


def test_read_recording_takes_the_columns_of_magnet_sample(tmp_path):
    rec = recording(7)
    write_csv(tmp_path / "r.csv", rec)
    back = read_recording(tmp_path / "r.csv")
    assert np.allclose(back.t_s, rec.t_s) and np.allclose(back.gyr_rads, rec.gyr_rads, atol=1e-4)
    write_csv(tmp_path / "nogyro.csv", recording(7, gyro=False))
    assert read_recording(tmp_path / "nogyro.csv").gyr_rads is None


@pytest.mark.parametrize(
    "text,message",
    [("mx,my,mz\n1,2,3\n", "needs a t_s column"), ("t_s,mx,my,mz\n0.2,1,2,3\n0.1,1,2,3\n", "go backwards at row 2")],
)
def test_edge_replay_refuses_a_bad_file_in_one_line(capsys, tmp_path, text, message):
    path = tmp_path / "bad.csv"
    path.write_text(text)
    code = main(["edge", "--replay", str(path), "--device", "r-1", "--no-multicast-scouting"])
    err = capsys.readouterr().err
    assert code == 2 and message in err and len(err.strip().splitlines()) == 1, err


def test_edge_replay_takes_no_emulation(capsys, tmp_path):
    code = main(["edge", "--replay", str(tmp_path / "r.csv"), "--emulate", "--no-multicast-scouting"])
    assert code == 2 and "--replay plays a recording" in capsys.readouterr().err


@pytest.mark.integration
def test_replay_arrives_complete_and_in_order_at_a_subscriber(tmp_path):
    rec = recording(47, rate_hz=100.0)
    write_csv(tmp_path / "flight.csv", rec)
    expected = read_recording(tmp_path / "flight.csv")
    batches, out = replay_raw(tmp_path / "flight.csv", "rep-1", "--speed", "2", "--batch", "10")
    assert [b.seq for b in batches] == [0, 1, 2, 3, 4] and [len(b) for b in batches] == [10, 10, 10, 10, 7]
    assert {b.sensor for b in batches} == {"replay"}
    t_ns = np.concatenate([b.t_ns for b in batches])
    assert np.array_equal(np.diff(t_ns), np.full(46, 10_000_000))  # the recorded 100 Hz, not scaled by speed

    def sent(values):  # wire v 2 carries measurements as <f4
        return np.asarray(values, dtype=np.float32).astype(float)

    assert np.array_equal(np.vstack([b.mag_ut for b in batches]), sent(expected.mag_ut))
    assert np.array_equal(np.vstack([b.acc_ms2 for b in batches]), sent(expected.acc_ms2))
    assert np.array_equal(np.vstack([b.gyr_rads for b in batches]), sent(expected.gyr_rads))
    summary = json.loads(out.stdout.strip().splitlines()[-1])
    assert summary["published_samples"] == 47 and summary["published_batches"] == 5
