"""The secure deployment as shipped: `magnet certs` -> a router with TLS (client certificates), a password listener
and access control -> every role does its job, and what a role may not do is refused.

Access control drops refused messages silently, so each refusal is checked against a marker: the same session then
sends something it may send on the same path; when the marker arrives, the refused message would have arrived
before it (one link, one priority, in order).
"""

from __future__ import annotations

import contextlib
import json
import re
import subprocess
import time
from collections.abc import Iterator
from pathlib import Path

import pytest
from helpers import MAGNET, REPO_ROOT, Processes, free_ports, wait_for

from services.security import acl

#: the steps of deploy/README.md, as the tests run them ($SITE: the directory; the ports are replaced by free ones)
STEPS = {
    "certs": "magnet certs --out $SITE --listen tls/127.0.0.1:7447 --password-listen tls/127.0.0.1:7448 "
    "--edge imu-host=imu-1",
    "keys": "magnet keys --out $SITE/signing --name calibrator",
    "router": "magnet router --config $SITE/router.json5",
    "calibrator": "magnet calibrator --config $SITE/calibrator.json5 --db $SITE/calibrations.db "
    "--signing-key $SITE/signing/calibrator.key",
    "standby": "magnet calibrator --config $SITE/calibrator.json5 --db $SITE/calibrations.db "
    "--signing-key $SITE/signing/calibrator.key --name calibrator-2",
    "compass": "magnet compass --config $SITE/compass.json5 --trust $SITE/signing/calibrator.pub",
    "edge": "magnet edge --config $SITE/edge-imu-host-password.json5 --device imu-1 --sensor sim --emulate "
    "--hard-iron 12,-7,4",
    "add-edge": "magnet certs --out $SITE --listen tls/127.0.0.1:7447 --password-listen tls/127.0.0.1:7448 "
    "--add --edge shed=imu-2,imu-3",
    "get": "magnet get calibration imu-1 --config $SITE/viewer.json5 --trust $SITE/signing/calibrator.pub",
    "watch": "magnet watch heading imu-1 --count 3 --config $SITE/viewer-password.json5",
    "calibrate": "magnet calibrate imu-1 status --config $SITE/operator.json5",
}
FAST_EDGE = ["--rate", "500", "--batch", "25", "--trajectory-samples", "2000"]
#: the identities the certs step makes (the edge role gives way to one identity per edge host)
IDENTITIES = [role for role in acl.ROLES if role != "edge"] + ["edge-imu-host"]


class Site(Processes):
    """A site directory from `magnet certs`, its ports, and the processes started for it."""

    def __init__(self, directory: Path) -> None:
        super().__init__(directory)
        self.dir = directory
        self.mtls_port, self.password_port = free_ports(2)

    def argv(self, step: str, *extra: str) -> list[str]:
        text = (
            STEPS[step]
            .replace("$SITE", str(self.dir))
            .replace("7447", str(self.mtls_port))
            .replace("7448", str(self.password_port))
        )
        return [*text.split()[1:], *extra]

    def run(self, step: str, *extra: str, timeout: float = 20) -> subprocess.CompletedProcess:
        return subprocess.run(
            [*MAGNET, *self.argv(step, *extra)], capture_output=True, text=True, timeout=timeout, cwd=REPO_ROOT
        )

    def start_step(self, step: str, *extra: str) -> None:
        self.start(step, *self.argv(step, *extra))

    def config(self, name: str):
        import zenoh

        return zenoh.Config.from_file(str(self.dir / f"{name}.json5"))


@pytest.fixture(scope="module")
def site(tmp_path_factory):
    s = Site(tmp_path_factory.mktemp("site"))
    for step in ("certs", "keys"):
        made = s.run(step)
        assert made.returncode == 0, made.stderr
    with routed(s):
        yield s


@contextlib.contextmanager
def routed(site: Site) -> Iterator[Site]:
    """``site`` with its router started and accepting clients; every process of the site stopped after."""
    site.start_step("router")
    try:
        wait_for(lambda: _opens(site.config("viewer")), 20, "the router to accept a client")
        yield site
    finally:
        site.stop_all()


def _opens(config) -> bool:
    import zenoh

    try:
        zenoh.open(config).close()
    except zenoh.ZError:
        return False
    return True


@pytest.mark.integration
def test_certs_are_v3_with_the_extensions_rustls_needs(site):
    from cryptography import x509
    from cryptography.x509.oid import ExtendedKeyUsageOID

    for role in ["router", *IDENTITIES]:
        cert = x509.load_pem_x509_certificate((site.dir / f"{role}.crt").read_bytes())
        assert cert.version == x509.Version.v3
        assert cert.subject.rfc4514_string() == f"CN={role}"
        assert not cert.extensions.get_extension_for_class(x509.BasicConstraints).value.ca
        usages = set(cert.extensions.get_extension_for_class(x509.ExtendedKeyUsage).value)
        assert ExtendedKeyUsageOID.CLIENT_AUTH in usages
        assert (ExtendedKeyUsageOID.SERVER_AUTH in usages) == (role == "router")
        names = cert.extensions.get_extension_for_class(x509.SubjectAlternativeName).value
        assert names.get_values_for_type(x509.DNSName) == ["localhost"]
        assert (site.dir / f"{role}.key").stat().st_mode & 0o777 == 0o600
    assert (site.dir / "users.txt").stat().st_mode & 0o777 == 0o600
    assert (site.dir / "ca.crt").stat().st_mode & 0o777 == 0o644
    again = site.run("certs")
    assert again.returncode == 2 and "already exist" in again.stderr, "nothing is overwritten"


@pytest.mark.integration
def test_every_role_does_its_job_through_the_secure_router(site):
    site.start_step("calibrator")
    site.start_step("compass")
    for service in ("calibrator", "compass"):
        wait_for(
            lambda service=service: (
                subprocess.run(
                    [*MAGNET, "get", "status", service, "--timeout", "1", "--config", str(site.dir / "viewer.json5")],
                    capture_output=True,
                    timeout=20,
                ).returncode
                == 0
            ),
            30,
            f"the {service} to answer",
        )
    site.start_step("edge", *FAST_EDGE)

    last = []

    def calibration():
        out = site.run("get", "--timeout", "2")
        last[:] = [out.stderr]
        return out.returncode == 0 and json.loads(out.stdout.splitlines()[0])

    try:
        record = wait_for(calibration, 60, "the calibrator (certificate) to store a calibration of the edge (password)")
    except BaseException:
        print("last get:", last, "\n".join(f"{name}: {site.log(name)[-2000:]}" for name in site.procs))
        raise
    assert record["accepted"] and record["device"] == "imu-1" and record["sig"], "a signed calibration"
    watched = site.run("watch", timeout=30)
    headings = [json.loads(line) for line in watched.stdout.splitlines()]
    assert watched.returncode == 0 and len(headings) == 3, watched.stderr
    assert all(h["calibration_id"] == record["id"] for h in headings), "headings use the calibration"
    operator = site.run("calibrate")
    assert operator.returncode == 0 and json.loads(operator.stdout)["state"] == "calibrated", operator.stderr
    viewer = subprocess.run(
        [*MAGNET, *site.argv("calibrate")[:-2], "--config", str(site.dir / "viewer.json5"), "--timeout", "2"],
        capture_output=True,
        text=True,
        timeout=20,
    )
    assert viewer.returncode == 1 and "no calibrator answered" in viewer.stderr, "a viewer cannot drive sessions"
    fleet = subprocess.run(
        [*MAGNET, "get", "fleet", "--config", str(site.dir / "viewer.json5"), "--timeout", "3"],
        capture_output=True,
        text=True,
        timeout=20,
    )
    assert fleet.returncode == 0, fleet.stderr
    assert [d["calibration_id"] for d in json.loads(fleet.stdout)["devices"]] == [record["id"]], (
        "a viewer sees the fleet"
    )
    for name in ("calibrator", "compass", "edge"):
        assert site.alive(name), site.log(name)


def _lease(site, name):
    out = subprocess.run(
        [*MAGNET, "get", "status", name, "--timeout", "1", "--config", str(site.dir / "viewer.json5")],
        capture_output=True,
        text=True,
        timeout=20,
    )
    return json.loads(out.stdout.splitlines()[0]) if out.returncode == 0 and out.stdout.strip() else None


@pytest.mark.integration  # starts a router and two calibrators
def test_a_second_calibrator_stands_by_and_takes_over_through_the_secure_router(site):
    if "calibrator" not in site.procs or not site.alive("calibrator"):
        site.start_step("calibrator")
    wait_for(lambda: _lease(site, "calibrator"), 30, "the calibrator to answer")
    site.start_step("standby")
    status = wait_for(lambda: _lease(site, "calibrator-2"), 30, "the second calibrator to answer")
    assert status["lease"] == "standby", "the access rules let calibrators see each other's lease tokens"
    assert _lease(site, "calibrator")["lease"] == "active"
    site.procs["calibrator"].kill()
    site.procs["calibrator"].wait()
    taken = wait_for(
        lambda: (s := _lease(site, "calibrator-2")) and s["lease"] == "active" and s, 20, "the standby to take over"
    )
    assert taken["takeovers"] == 1 and site.alive("standby")


def _payloads(channel) -> list[bytes]:
    out = []
    while (item := channel.try_recv()) is not None:
        if getattr(item, "payload", None) is not None:
            out.append(item.payload.to_bytes())
    return out


def _marker_check(channel_refused, channel_marker, send_refused, send_marker, timeout_s=10.0) -> list[bytes]:
    """Send the refused message then a marker, repeatedly, until a marker arrives; returns what the refused
    message's channel holds then (the refused payload must not be among it)."""
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        send_refused()
        send_marker()
        stop = time.monotonic() + 0.3
        while time.monotonic() < stop:
            if channel_marker.try_recv() is not None:
                return _payloads(channel_refused)
            time.sleep(0.01)
    pytest.fail("the marker never arrived: the allowed path does not work")


@pytest.mark.integration
def test_what_a_role_may_not_do_is_refused(site):
    import zenoh

    with (
        zenoh.open(site.config("viewer")) as viewer,
        zenoh.open(site.config("compass")) as compass,
        zenoh.open(site.config("edge-imu-host")) as edge,
        zenoh.open(site.config("calibrator")) as calibrator,
    ):
        cal_sub = viewer.declare_subscriber("magnet/probe-1/calibration")
        heading_sub = viewer.declare_subscriber("magnet/probe-1/heading")
        own_raw = _Only(viewer.declare_subscriber("magnet/imu-1/raw"), b"r")
        raw_sub = calibrator.declare_subscriber("magnet/probe-1/raw")
        status_q = calibrator.declare_queryable("magnet/@status/probe")
        # the allowed put arrives (and so the subscriptions are in place)
        _marker_check(heading_sub, cal_sub, lambda: None, lambda: calibrator.put("magnet/probe-1/calibration", b"ok"))
        # a compass cannot put a calibration: its heading arrives, the calibration does not
        assert b"forged" not in _marker_check(
            cal_sub,
            heading_sub,
            lambda: compass.put("magnet/probe-1/calibration", b"forged"),
            lambda: compass.put("magnet/probe-1/heading", b"h"),
        )
        # nor can an edge (its marker: raw samples of its own device)
        assert b"forged" not in _marker_check(
            cal_sub,
            own_raw,
            lambda: edge.put("magnet/probe-1/calibration", b"forged"),
            lambda: edge.put("magnet/imu-1/raw", b"r"),
        )
        # a viewer cannot put raw samples: its query reaches the calibrator's status queryable after its put
        assert b"forged" not in _marker_check(
            raw_sub,
            status_q,
            lambda: viewer.put("magnet/probe-1/raw", b"forged"),
            lambda: viewer.get("magnet/@status/probe", timeout=0.2),
        )
        # a compass cannot serve calibrations: its refused queryable is never asked
        fake = compass.declare_queryable("magnet/probe-2/calibration")
        compass_status = compass.declare_queryable("magnet/@status/probe-compass")
        wait_for(
            lambda: _answered(viewer, compass_status, "magnet/@status/probe-compass"),
            10,
            "the compass's allowed queryable to answer",
        )
        replies = list(viewer.get("magnet/probe-2/calibration", timeout=1.0))
        assert fake.try_recv() is None and replies == [], "a compass's calibration queryable is never asked"


class _Only:
    """The samples of a subscriber that carry ``payload`` (a marker among other traffic on the same key)."""

    def __init__(self, channel, payload):
        self.channel, self.payload = channel, payload

    def try_recv(self):
        while (item := self.channel.try_recv()) is not None:
            if item.payload.to_bytes() == self.payload:
                return item
        return None


def _answered(session, queryable, key):
    replies = session.get(key, timeout=0.5)
    deadline = time.monotonic() + 0.5
    while time.monotonic() < deadline:
        query = queryable.try_recv()
        if query is not None:
            query.reply(key, b"ok")
            query.drop()
            break
        time.sleep(0.01)
    return any(reply.ok is not None for reply in replies)


@pytest.mark.integration
def test_unauthenticated_and_wrong_ca_clients_are_refused(site, tmp_path):
    import zenoh

    other = subprocess.run(
        [*MAGNET, "certs", "--out", str(tmp_path / "other")], capture_output=True, text=True, timeout=30
    )
    assert other.returncode == 0, other.stderr
    # a certificate from another CA (the client trusts the right CA, so only the router's check can refuse it)
    wrong_ca = site.config("calibrator")
    wrong_ca.insert_json5("transport/link/tls/connect_certificate", json.dumps(str(tmp_path / "other/calibrator.crt")))
    wrong_ca.insert_json5("transport/link/tls/connect_private_key", json.dumps(str(tmp_path / "other/calibrator.key")))
    no_cert = site.config("viewer-password")  # TLS without a client certificate, on the mTLS listener
    no_cert.insert_json5("connect/endpoints", json.dumps([f"tls/127.0.0.1:{site.mtls_port}"]))
    bad_password = site.config("edge-imu-host-password")
    bad_password.insert_json5("transport/auth/usrpwd/password", '"guessed"')
    plain = zenoh.Config()
    for key, value in (
        ("mode", '"client"'),
        ("connect/endpoints", json.dumps([f"tcp/127.0.0.1:{site.mtls_port}"])),
        ("scouting/multicast/enabled", "false"),
    ):
        plain.insert_json5(key, value)
    with zenoh.open(site.config("edge-imu-host-password")):
        pass  # the right password on the password listener is let in
    for name, config in (
        ("wrong CA", wrong_ca),
        ("no certificate", no_cert),
        ("bad password", bad_password),
        ("plain TCP", plain),
    ):
        try:
            zenoh.open(config).close()
        except zenoh.ZError:
            continue  # refused, as it must be
        pytest.fail(f"{name}: the router let it in")


def test_deploy_readme_steps_are_the_tested_ones():
    readme = (REPO_ROOT / "deploy" / "README.md").read_text()
    for step, command in STEPS.items():
        assert command in readme, f"deploy/README.md lacks the tested step {step}: {command}"


def test_shipped_router_config_is_what_magnet_certs_writes():
    site = acl.Site("tls/0.0.0.0:7447", "tls/0.0.0.0:7448", Path("/etc/magnet/tls"))
    shipped = (REPO_ROOT / "deploy" / "router-secure.json5").read_text()
    body = shipped[shipped.index("{") :]
    assert json.loads(body) == acl.router_config(site)
    assert re.search(r"magnet certs", shipped)
