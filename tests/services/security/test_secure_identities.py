"""One identity per edge host and per calibrator shard, through the real TLS router with access control (the site of
deploy/README.md, made with `magnet certs --edge imu-host=imu-1 --shards 2`): an edge login speaks only for its own
devices (samples for another never reach a calibrator), its unhealthy token and status pass, a lease token counts
only from its shard's calibrator identity, and an edge host added later (`--add`) gets only its own devices.

Refusals are checked against a marker the same session may send on the same path (see test_secure_deploy.py)."""

from __future__ import annotations

import json
import subprocess
import time

import pytest
from helpers import MAGNET, wait_for
from test_secure_deploy import FAST_EDGE, Site, _lease, _marker_check, _Only, _opens, _payloads, routed

pytestmark = pytest.mark.integration


@pytest.fixture(scope="module")
def site(tmp_path_factory):
    s = Site(tmp_path_factory.mktemp("idsite"))
    for made in (s.run("certs", "--shards", "2"), s.run("keys")):
        assert made.returncode == 0, made.stderr
    with routed(s):
        yield s


@pytest.fixture(scope="module")
def trial_site(tmp_path_factory):
    """A site made without --edge: the edge role (any device), as before."""
    s = Site(tmp_path_factory.mktemp("trial"))
    made = subprocess.run(
        [*MAGNET, *s.argv("certs")[:-2]], capture_output=True, text=True, timeout=30
    )  # the same command without --edge
    assert made.returncode == 0, made.stderr
    with routed(s):
        yield s


def _get(site, *args, config="viewer"):
    return subprocess.run(
        [*MAGNET, *args, "--timeout", "2", "--config", str(site.dir / f"{config}.json5")],
        capture_output=True,
        text=True,
        timeout=30,
    )


def test_an_edge_login_speaks_only_for_its_own_devices(site):
    import zenoh

    with (
        zenoh.open(site.config("edge-imu-host-password")) as edge,
        zenoh.open(site.config("calibrator")) as calibrator,
    ):
        stranger = calibrator.declare_subscriber("magnet/intruder-1/raw")
        own = _Only(calibrator.declare_subscriber("magnet/imu-1/raw"), b"marker")
        assert b"forged" not in _marker_check(
            stranger,
            own,
            lambda: edge.put("magnet/intruder-1/raw", b"forged"),
            lambda: edge.put("magnet/imu-1/raw", b"marker"),
        )
        assert _payloads(stranger) == []


def test_samples_for_a_device_the_edge_was_not_issued_for_never_reach_the_calibrator(site):
    site.start("calibrator", *site.argv("calibrator"))
    wait_for(lambda: _lease(site, "calibrator"), 30, "the calibrator to answer")
    site.start_step("edge", "--device", "intruder-1", *FAST_EDGE)  # the same login, another device id
    site.start("edge-own", *site.argv("edge"), *FAST_EDGE)

    def fleet():
        out = _get(site, "get", "fleet")
        return out.returncode == 0 and json.loads(out.stdout)["devices"]

    devices = wait_for(lambda: (d := fleet()) and any(e["device"] == "imu-1" for e in d) and d, 30, "imu-1 seen")
    time.sleep(2.0)  # the intruder edge has been publishing all along
    devices = fleet()
    assert [e["device"] for e in devices] == ["imu-1"], "intruder-1's samples were dropped at the router"
    status = _lease(site, "calibrator")
    assert status["received_batches"] > 0 and site.alive("edge"), site.log("edge")
    print(f"calibrator saw devices {[e['device'] for e in devices]}, received_batches {status['received_batches']}")


def test_the_edge_s_unhealthy_token_and_its_status_pass_the_router(site):
    import zenoh

    if "edge-own" not in site.procs or not site.alive("edge-own"):
        site.start("edge-own", *site.argv("edge"), *FAST_EDGE)
    status = wait_for(lambda: (out := _get(site, "get", "status", "edge-imu-1")).returncode == 0 and out, 30, "status")
    assert json.loads(status.stdout.splitlines()[0])["name"] == "edge-imu-1"
    with zenoh.open(site.config("edge-imu-host-password")) as edge, zenoh.open(site.config("viewer")) as viewer:
        token = edge.liveliness().declare_token("magnet/@alive/device/imu-1/unhealthy")

        def seen():
            replies = viewer.liveliness().get("magnet/@alive/device/imu-1/**", timeout=1.0)
            return {str(r.ok.key_expr) for r in replies if r.ok is not None}

        wait_for(lambda: "magnet/@alive/device/imu-1/unhealthy" in seen(), 10, "the unhealthy token at a viewer")
        token.undeclare()


def test_the_trial_edge_role_declares_unhealthy_tokens_and_serves_its_status(trial_site):
    import zenoh

    with zenoh.open(trial_site.config("edge-password")) as edge, zenoh.open(trial_site.config("viewer")) as viewer:
        token = edge.liveliness().declare_token("magnet/@alive/device/any-1/unhealthy")
        status = edge.declare_queryable("magnet/@status/edge-any-1")
        forged = edge.declare_queryable("magnet/@status/calibrator")

        def seen():
            replies = viewer.liveliness().get("magnet/@alive/device/any-1/**", timeout=1.0)
            return {str(r.ok.key_expr) for r in replies if r.ok is not None}

        wait_for(lambda: "magnet/@alive/device/any-1/unhealthy" in seen(), 10, "the unhealthy token at a viewer")
        from test_secure_deploy import _answered

        wait_for(lambda: _answered(viewer, status, "magnet/@status/edge-any-1"), 10, "the edge's status to answer")
        assert not list(viewer.get("magnet/@status/calibrator", timeout=1.0)) and forged.try_recv() is None
        token.undeclare()


def test_a_lease_token_counts_only_from_its_shard_s_calibrator_identity(site):
    import zenoh

    site.start(
        "cal-1",
        "calibrator",
        "--config",
        str(site.dir / "calibrator-1-2.json5"),
        "--shard",
        "1/2",
        "--name",
        "cal-1",
        "--db",
        str(site.dir / "shard1.db"),
    )
    wait_for(lambda: (s := _lease(site, "cal-1")) and s["lease"] == "active", 30, "cal-1 to hold its lease")
    fake = "magnet/@lease/calibrator/1-2/0/fake"  # started at 0 ns: the oldest, it would hold the lease
    for identity in ("calibrator-0-2", "calibrator"):
        with zenoh.open(site.config(identity)) as other:
            other.liveliness().declare_token(fake)
            time.sleep(2.0)
            assert _lease(site, "cal-1")["lease"] == "active", f"{identity}'s token for shard 1/2 was let through"
    with zenoh.open(site.config("calibrator-1-2")) as same_shard:  # the control: the shard's own identity counts
        token = same_shard.liveliness().declare_token(fake)
        wait_for(lambda: _lease(site, "cal-1")["lease"] == "standby", 10, "the shard's own token to count")
        token.undeclare()
        wait_for(lambda: _lease(site, "cal-1")["lease"] == "active", 10, "cal-1 to take its lease back")


def test_an_edge_host_added_later_speaks_for_its_own_devices_only(site):
    import zenoh

    before = (site.dir / "edge-imu-host.crt").read_bytes(), (site.dir / "users.txt").read_text()
    added = site.run("add-edge")
    assert added.returncode == 0, added.stderr
    assert (site.dir / "edge-imu-host.crt").read_bytes() == before[0], "existing certificates untouched"
    users = (site.dir / "users.txt").read_text()
    assert before[1].splitlines()[0] in users.splitlines() and "edge-shed:" in users, "passwords kept, one added"
    saved = json.loads((site.dir / "site.json").read_text())
    assert saved["edges"] == {"imu-host": ["imu-1"], "shed": ["imu-2", "imu-3"]} and saved["shards"] == 2
    site.procs["router"].terminate()
    site.procs["router"].wait(timeout=10)
    site.start_step("router")
    wait_for(lambda: _opens(site.config("edge-shed-password")), 20, "the router to let the new edge in")
    with zenoh.open(site.config("edge-shed-password")) as shed, zenoh.open(site.config("calibrator")) as calibrator:
        other = calibrator.declare_subscriber("magnet/imu-1/raw")
        own = _Only(calibrator.declare_subscriber("magnet/imu-3/raw"), b"marker")
        assert b"forged" not in _marker_check(
            other,
            own,
            lambda: shed.put("magnet/imu-1/raw", b"forged"),
            lambda: shed.put("magnet/imu-3/raw", b"marker"),
        )
