"""``magnet up`` and the client tools find each other: beside a running ``magnet up``, ``magnet get fleet`` and
``magnet watch heading DEVICE`` given no Zenoh option reach it through the per-user runtime file; the file goes
when ``up`` stops, and the ``--connect`` line ``up`` prints reaches the same pipeline from a script."""

from __future__ import annotations

import json
import os
import re
import signal
import subprocess

import pytest
from helpers import MAGNET, REPO_ROOT, wait_for

pytestmark = pytest.mark.integration


def magnet(env, *args, timeout=30):
    return subprocess.run(
        [*MAGNET, *args],
        capture_output=True,
        text=True,
        timeout=timeout,
        env=env,
        cwd=REPO_ROOT,
        stdin=subprocess.DEVNULL,
    )


def on_a_terminal(env, *args, timeout=30):
    """What ``magnet ARGS`` prints when its stdout is a terminal (a pseudo-terminal, 200 columns)."""
    import pty

    main, child = pty.openpty()
    try:
        done = subprocess.run(
            [*MAGNET, *args],
            stdout=child,
            stderr=subprocess.PIPE,
            stdin=subprocess.DEVNULL,
            timeout=timeout,
            env={**env, "COLUMNS": "200", "TERM": "xterm"},
            cwd=REPO_ROOT,
        )
        os.close(child)
        child = -1
        chunks = []
        while True:
            try:
                chunk = os.read(main, 65536)
            except OSError:  # the terminal's other side is closed: everything was read
                break
            if not chunk:
                break
            chunks.append(chunk)
    finally:
        os.close(main)
        if child >= 0:
            os.close(child)
    assert done.returncode == 0, done.stderr
    return re.sub(r"\x1b\[[0-9;?]*[a-zA-Z]", "", b"".join(chunks).decode(errors="replace"))


def test_get_fleet_and_watch_heading_beside_magnet_up_need_no_options(tmp_path):
    runtime = tmp_path / "run"
    runtime.mkdir(mode=0o700)
    env = {**os.environ, "CI": "true", "XDG_RUNTIME_DIR": str(runtime)}
    with open(tmp_path / "up.out", "w") as out:
        up = subprocess.Popen(
            [*MAGNET, "up", "--devices", "2", "--speedup", "10", "--no-dashboard", "--duration", "90",
             "--interval", "5", "--db", str(tmp_path / "up.db")],
            stdout=out, stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL, env=env, cwd=REPO_ROOT,
        )  # fmt: skip
    try:
        record_path = runtime / "magnet" / f"up-{up.pid}.json"
        wait_for(lambda: record_path.exists() or up.poll() is not None, 30, "the runtime file")
        record = json.loads(record_path.read_text())
        assert record["pid"] == up.pid and set(record["ports"]) == {"calibrator", "compass", "edge"}
        assert oct(record_path.stat().st_mode & 0o777) == "0o600"
        printed = (tmp_path / "up.out").read_text()
        assert re.search(r"calibrator 127\.0\.0\.1:\d+, compass 127\.0\.0\.1:\d+, edge 127\.0\.0\.1:\d+", printed)
        line = re.search(r"give them: (.+)$", printed, re.M).group(1).split()
        assert line[0] == "--no-multicast-scouting" and line.count("--connect") == 3, line

        def fleet():
            done = magnet(env, "get", "fleet")
            if done.returncode != 0:
                return None
            devices = json.loads(done.stdout.splitlines()[0])["devices"]
            return devices if {d["device"] for d in devices} >= {"dev-000", "dev-001"} else None

        devices = wait_for(fleet, 40, "magnet get fleet with no options to list both devices")
        assert all("alerts" in d for d in devices)
        watched = magnet(env, "watch", "heading", "dev-001", "--count", "3", "--duration", "20")
        messages = [json.loads(x) for x in watched.stdout.splitlines() if x.strip()]
        assert watched.returncode == 0 and len(messages) == 3, watched.stderr
        assert {m["device"] for m in messages} == {"dev-001"} and all(
            m["key"] == "magnet/dev-001/heading" for m in messages
        )
        table = on_a_terminal(env, "get", "fleet")
        assert "\u2503" in table and "dev-001" in table and "residual uT" in table, table  # a drawn table
        as_json = on_a_terminal(env, "get", "fleet", "--json")
        assert json.loads(as_json.strip().splitlines()[0])["count"] >= 2, as_json  # --json: JSON even on a terminal
        elsewhere = magnet({**env, "XDG_RUNTIME_DIR": str(tmp_path / "nowhere")}, "get", "fleet", *line)
        assert elsewhere.returncode == 0 and json.loads(elsewhere.stdout.splitlines()[0])["devices"]
        joined = subprocess.Popen(  # a second compass given no Zenoh option joins the pipeline (so would an edge)
            [*MAGNET, "compass", "--name", "second"], stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
            stdin=subprocess.DEVNULL, env=env, cwd=REPO_ROOT,
        )  # fmt: skip
        try:
            wait_for(lambda: magnet(env, "get", "status", "second").returncode == 0 or None, 30, "the joined compass")
        finally:
            joined.terminate()
            joined.wait(timeout=15)
        exported = wait_for(  # export --device finds the pipeline's calibrator (once dev-000 is calibrated)
            lambda: (lambda done: done if done.returncode == 0 else None)(
                magnet(env, "export", "--device", "dev-000", "--format", "px4")
            ),
            60,
            "magnet export --device dev-000 with no options",
        )
        assert "CAL_MAG0_XOFF" in exported.stdout and "from the device id dev-000" not in exported.stderr
        bag = tmp_path / "up.mcap"  # magnet record finds the pipeline too, hears its devices, and writes the
        recorded = magnet(env, "record", "--out", str(bag), "--seconds", "3")  # calibrations in force at its start
        assert recorded.returncode == 0 and bag.exists(), recorded.stderr
        written = json.loads(recorded.stdout.splitlines()[-1])["written"]
        assert written["sensor_msgs/msg/MagneticField"] > 0 and written["std_msgs/msg/String"] >= 1, written
    finally:
        up.send_signal(signal.SIGTERM)
        up.wait(timeout=30)
    assert not record_path.exists(), "the runtime file goes with the pipeline"
    gone = magnet(env, "get", "fleet", "--timeout", "1", "--no-multicast-scouting")  # no file: nothing to reach
    assert gone.returncode == 1 and "no calibrator answered" in gone.stderr
