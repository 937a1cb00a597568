"""Hosts that part and heal: a router, an edge host and a services host, each in its own Linux network namespace,
joined by veth links with link-local /30 addresses that exist only inside these namespaces (the test's own hosts).
The edge's link to the router is cut for longer than Zenoh's lease and restored: headings resume by themselves, the
calibrator receives again, no stored calibration is lost, and ``magnet get`` from the edge host answers again. Prints
how long the headings took to resume. Skips, saying why, where the machine cannot make network namespaces (needs
root and ``ip netns``); namespaces and processes are removed in a finalizer whatever happens.
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import threading
import time
from pathlib import Path

import numpy as np
import pytest
from helpers import MAGNET, REPO_ROOT, wait_for

from magnet import wire
from magnet.model import Calibration, Quality
from services.calibrator.store import CalibrationStore
from services.common.processes import stop_processes

pytestmark = pytest.mark.integration

TAG = f"mg{os.getpid() % 100000}"
ROUTER, EDGE, SERVICES = f"{TAG}-r", f"{TAG}-e", f"{TAG}-s"
#: (namespace, its veth, its address; the router's veth, the router's address) per link, /30 each
LINKS = {EDGE: ("ve0", "169.254.77.2", "vr0", "169.254.77.1"), SERVICES: ("vs0", "169.254.78.2", "vr1", "169.254.78.1")}
PORT = 7447
DEVICE = "p-1"
CUT_S = 14.0  # longer than Zenoh's default lease (10 s): the sessions must really re-form
RESUME_BOUND_S = 60.0


def sh(*args: str) -> None:
    subprocess.run(args, check=True, capture_output=True, timeout=20)


def netns_exec(ns: str, *args: str) -> list[str]:
    return ["ip", "netns", "exec", ns, *args]


def client(ns: str) -> list[str]:
    router_address = LINKS[ns][3]
    return ["--mode", "client", "--no-multicast-scouting", "--connect", f"tcp/{router_address}:{PORT}"]


@pytest.fixture
def site(tmp_path):
    """Three namespaces joined through the router's; removed (with every process started) at the end."""
    if shutil.which("ip") is None:
        pytest.skip("no `ip` command (iproute2): cannot make network namespaces")
    probe = subprocess.run(["ip", "netns", "add", ROUTER], capture_output=True, text=True)
    if probe.returncode != 0:
        pytest.skip(
            f"cannot make network namespaces here (`ip netns add` failed: {probe.stderr.strip()}); "
            "the partition test needs root and a kernel with network namespaces"
        )
    procs: list[subprocess.Popen] = []
    logs: list = []
    try:
        for ns in (EDGE, SERVICES):
            sh("ip", "netns", "add", ns)
        for ns in (ROUTER, EDGE, SERVICES):
            sh("ip", "-n", ns, "link", "set", "lo", "up")
        for ns, (veth, address, router_veth, router_address) in LINKS.items():
            sh(
                "ip",
                "link",
                "add",
                f"{TAG}{veth}",
                "netns",
                ns,
                "type",
                "veth",
                "peer",
                "name",
                f"{TAG}{router_veth}",
                "netns",
                ROUTER,
            )
            sh("ip", "-n", ns, "addr", "add", f"{address}/30", "dev", f"{TAG}{veth}")
            sh("ip", "-n", ROUTER, "addr", "add", f"{router_address}/30", "dev", f"{TAG}{router_veth}")
            sh("ip", "-n", ns, "link", "set", f"{TAG}{veth}", "up")
            sh("ip", "-n", ROUTER, "link", "set", f"{TAG}{router_veth}", "up")
        yield Site(tmp_path, procs, logs)
    finally:
        stop_processes(procs)
        for proc in procs:
            if proc.stdout is not None:
                proc.stdout.close()
        for log in logs:
            log.close()
        for ns in (ROUTER, EDGE, SERVICES):
            subprocess.run(["ip", "netns", "del", ns], capture_output=True)


class Site:
    def __init__(self, tmp_path: Path, procs: list[subprocess.Popen], logs: list) -> None:
        self.tmp_path, self.procs, self.logs = tmp_path, procs, logs

    def start(self, name: str, ns: str, *args: str, stdout=None) -> subprocess.Popen:
        log = open(self.tmp_path / f"{name}.log", "w")  # noqa: SIM115 - open while the process runs; closed at the end
        self.logs.append(log)
        proc = subprocess.Popen(
            netns_exec(ns, *MAGNET, *args), cwd=REPO_ROOT, stdout=stdout or log, stderr=log, text=True
        )
        self.procs.append(proc)
        return proc

    def magnet_json(self, ns: str, *args: str) -> tuple[int, list]:
        out = subprocess.run(
            netns_exec(ns, *MAGNET, *args, *client(ns), "--timeout", "2"),
            cwd=REPO_ROOT,
            capture_output=True,
            text=True,
            timeout=30,
        )
        return out.returncode, [json.loads(line) for line in out.stdout.splitlines() if line.strip()]

    def link(self, ns: str, up: bool) -> None:
        sh("ip", "-n", ns, "link", "set", f"{TAG}{LINKS[ns][0]}", "up" if up else "down")


def stored_calibration(path: Path) -> str:
    cal = Calibration(
        "ellipsoid",
        np.array([20.0, -10.0, 5.0]),
        np.eye(3),
        field_strength=51.0,
        quality=Quality(residual_rms_ut=0.3, coverage=0.95),
        accepted=True,
    )
    with CalibrationStore(path) as store:
        store.save(wire.DeviceCalibration(DEVICE, time.time_ns(), cal))
    return cal.content_id


class Headings:
    """Arrival times (monotonic s) of the heading messages a ``magnet watch heading`` process prints."""

    def __init__(self, proc: subprocess.Popen) -> None:
        self.times: list[float] = []
        self.last: dict = {}
        threading.Thread(target=self._read, args=(proc,), daemon=True).start()

    def _read(self, proc: subprocess.Popen) -> None:
        for line in proc.stdout or ():
            if line.strip():
                self.last = json.loads(line)
                self.times.append(time.monotonic())

    def since(self, t: float) -> list[float]:
        return [x for x in self.times if x > t]


def test_a_cut_link_heals_headings_resume_and_nothing_stored_is_lost(site):
    db = site.tmp_path / "cal.db"
    cal_id = stored_calibration(db)
    router_listen = [a for ns in LINKS for a in ("--listen", f"tcp/{LINKS[ns][3]}:{PORT}")]
    site.start("router", ROUTER, "router", "--no-multicast-scouting", *router_listen)
    site.start("calibrator", SERVICES, "calibrator", "--db", str(db), *client(SERVICES))
    site.start("compass", SERVICES, "compass", "--location", "50.45,30.52", *client(SERVICES))
    watcher = Headings(
        site.start("watch", SERVICES, "watch", "heading", DEVICE, *client(SERVICES), stdout=subprocess.PIPE)
    )
    site.start(
        "edge",
        EDGE,
        "edge",
        "--device",
        DEVICE,
        "--emulate",
        "--rate",
        "50",
        "--batch",
        "5",
        "--hard-iron",
        "20,-10,5",
        *client(EDGE),
    )
    wait_for(
        lambda: len(watcher.times) >= 20 and watcher.last.get("calibration_id") == cal_id,
        60,
        "calibrated headings to flow from the edge host to the services host",
    )
    code, [before] = site.magnet_json(SERVICES, "get", "status", "calibrator")
    assert code == 0 and before["received_batches"] > 0

    site.link(EDGE, up=False)
    cut_at = time.monotonic()
    code, _ = site.magnet_json(EDGE, "get", "calibration", DEVICE)
    assert code != 0, "the edge host still reaches the calibrator: the link is not cut"
    time.sleep(max(0.0, CUT_S - (time.monotonic() - cut_at)))  # the partition itself: nothing to wait for
    during = len(watcher.since(cut_at + 2.0))
    site.link(EDGE, up=True)
    healed_at = time.monotonic()

    first = wait_for(lambda: watcher.since(healed_at), RESUME_BOUND_S, "headings to resume after the link healed")[0]
    resumed_s = first - healed_at
    print(
        f"partition of {CUT_S:.0f} s: headings resumed {resumed_s:.2f} s after the link came back "
        f"({during} heading messages arrived during the cut)"
    )
    assert during == 0, "headings arrived while the link was cut"
    wait_for(lambda: len(watcher.since(healed_at)) >= 20, 30, "headings to keep flowing")
    assert watcher.last["calibration_id"] == cal_id
    after = wait_for(
        lambda: (
            (s := site.magnet_json(SERVICES, "get", "status", "calibrator")[1])
            and s[0]["received_batches"] > before["received_batches"] + 10
            and s[0]
        ),
        30,
        "the calibrator to receive raw batches again",
    )
    assert after["received_batches"] > before["received_batches"]
    code, [served] = wait_for(
        lambda: (r := site.magnet_json(EDGE, "get", "calibration", DEVICE))[0] == 0 and r,
        30,
        "magnet get to answer from the edge host again",
    )
    assert served["id"] == cal_id
    with CalibrationStore(db) as store:
        assert [r.id for r in store.history(DEVICE)] == [cal_id]
    for proc in site.procs:
        assert proc.poll() is None, f"a service ended: {proc.args}"
