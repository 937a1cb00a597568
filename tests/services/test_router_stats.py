"""Messages the router's access control denies, counted from Zenoh's access-control log: the lines as Zenoh writes
them (captured from zenoh 1.10 with ANSI colours), the log filter, the pipe that swallows them and passes the rest
on; and (integration) a real ``magnet router`` with access-control rules whose status counts the denied puts of a
client."""

from __future__ import annotations

import json
import os
import threading
import time

import pytest
from helpers import NO_SCOUT, connect_args, free_ports, magnet_json, wait_for

from services.common.router_stats import ACL_TARGET, AclDenials, _forward, log_filter

ZID = "a187fe601f6c25da1e0d7b379eace7cc"
SUBJECT = f"Interface(lo)+Transport(Tcp)+{ZID}"
DENIED = (
    f"2026-12-01T21:46:55.536316Z \x1b[35mTRACE\x1b[0m rx-1 ThreadId(09) \x1b[2m{ACL_TARGET}\x1b[0m\x1b[2m:\x1b[0m "
    f"{ZID} on {SUBJECT} is unauthorized to Put (ingress) on magnet/intruder-1/raw"
)
CACHED = f"... TRACE rx-1 {ACL_TARGET}: Using cached result: {ZID} is unauthorized to Put (ingress) on magnet/x/raw"
ALLOWED = f"... TRACE rx-1 {ACL_TARGET}: {ZID} on {SUBJECT} is authorized to Put (ingress) on magnet/imu-1/raw"
OTHER = "2026-12-01T21:46:55Z WARN zenoh::net::runtime: something else"


def test_denied_lines_are_counted_by_kind_and_key_and_every_access_control_line_is_swallowed():
    denials = AclDenials()
    assert [denials.feed(line) for line in (DENIED, CACHED, ALLOWED, OTHER, DENIED)] == [True, True, True, False, True]
    assert denials.to_dict() == {
        "acl_denied": 3,
        "acl_denied_by": {"Put (ingress)": 3},
        "acl_denied_keys": {"magnet/intruder-1/raw": 2, "magnet/x/raw": 1},
    }


def test_the_keys_remembered_are_bounded():
    denials = AclDenials(max_keys=4)
    for i in range(100):
        denials.feed(DENIED.replace("intruder-1", f"flood-{i}"))
    assert denials.total == 100 and len(denials.by_key) == 4


def test_the_log_filter_adds_the_access_control_module_and_keeps_the_rest_quiet():
    assert log_filter(None) == f"off,{ACL_TARGET}=trace"
    assert log_filter("info") == f"info,{ACL_TARGET}=trace"


def test_the_pipe_counts_and_swallows_access_control_lines_and_passes_the_others_on():
    denials = AclDenials()
    in_read, in_write = os.pipe()
    out_read, out_write = os.pipe()
    thread = threading.Thread(target=_forward, args=(in_read, out_write, denials))
    thread.start()
    text = "\n".join([OTHER, DENIED, ALLOWED, "plain line", CACHED]) + "\ntail without newline"
    for start in range(0, len(text), 37):  # lines cut across reads
        os.write(in_write, text[start : start + 37].encode())
    os.close(in_write)
    thread.join(timeout=5)
    os.close(out_write)
    passed = os.read(out_read, 1 << 16).decode()
    os.close(in_read)
    os.close(out_read)
    assert passed == f"{OTHER}\nplain line\ntail without newline"
    assert denials.total == 2


ACL = {
    "enabled": True,
    "default_permission": "deny",
    "rules": [
        {
            "id": "own-device",
            "messages": ["put", "declare_subscriber", "query", "reply", "declare_queryable", "liveliness_token"],
            "flows": ["ingress", "egress"],
            "permission": "allow",
            "key_exprs": ["magnet/imu-1/raw", "magnet/@status/**", "magnet/@alive/**"],
        }
    ],
    "subjects": [{"id": "loopback", "interfaces": ["lo"]}],
    "policies": [{"rules": ["own-device"], "subjects": ["loopback"]}],
}


@pytest.mark.integration
def test_the_router_counts_the_messages_its_access_control_denies(procs, tmp_path):
    import zenoh

    (port,) = free_ports(1)
    config = tmp_path / "router.json5"
    config.write_text(
        json.dumps(
            {
                "mode": "router",
                "listen": {"endpoints": [f"tcp/127.0.0.1:{port}"]},
                "scouting": {"multicast": {"enabled": False}},
                "access_control": ACL,
            }
        )
    )
    procs.start("router", "router", "--config", str(config), "--name", "r1")

    def status():
        code, lines = magnet_json("get", "status", "r1", *NO_SCOUT, *connect_args(port), "--timeout", "2")
        return lines[0] if code == 0 and lines else None

    before = wait_for(status, 30, "the router's status")
    assert before["acl_denied"] == 0, before
    conf = zenoh.Config()
    conf.insert_json5("connect/endpoints", json.dumps([f"tcp/127.0.0.1:{port}"]))
    conf.insert_json5("scouting/multicast/enabled", "false")
    with zenoh.open(conf) as session:
        for _ in range(25):
            session.put("magnet/intruder-1/raw", b"forged")  # denied
            session.put("magnet/imu-1/raw", b"own")  # allowed
        time.sleep(0.5)
    after = wait_for(lambda: (s := status()) and s["acl_denied"] >= 25 and s, 10, "25 denied puts counted")
    assert after["acl_denied_by"]["Put (ingress)"] >= 25
    assert after["acl_denied_keys"]["magnet/intruder-1/raw"] == 25
    assert "magnet/imu-1/raw" not in after["acl_denied_keys"]
    assert procs.alive("router"), procs.log("router")
