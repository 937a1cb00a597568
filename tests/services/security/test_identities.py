"""Identities narrower than a role (services/security/identities.py) and the access-control rules made of them; the
`magnet certs --edge/--shards/--add` options. The router applying them is tested in test_secure_identities.py."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from services.cli import main
from services.security import acl, identities


def _keys(rules, rule_id):
    return next(rule["key_exprs"] for rule in rules if rule["id"] == rule_id)


def test_an_edge_identity_may_write_only_its_own_devices_keys():
    edge = identities.parse_edge("barn=imu-1, imu-2")
    assert edge.identity == "edge-barn" and edge.devices == ("imu-1", "imu-2")
    rules = acl.rules("magnet", acl.site_roles([edge]))
    assert _keys(rules, "edge-barn-ingress-put") == ["magnet/imu-1/raw", "magnet/imu-2/raw"]
    assert "magnet/@alive/device/imu-1/unhealthy" in _keys(rules, "edge-barn-ingress-liveliness_token")
    assert _keys(rules, "edge-barn-ingress-declare_queryable+reply") == [
        "magnet/@status/edge-imu-1",
        "magnet/@status/edge-imu-2",
    ]
    assert not any(rule["id"].startswith("edge-ingress") for rule in rules), "no edge role that speaks for any device"
    everything = [key for rule in rules if rule["id"].startswith("edge-barn-ingress") for key in rule["key_exprs"]]
    assert not any("*" in key for key in everything), "no wildcard in what it may send"


def test_policies_hold_only_their_own_identity_s_rules():
    roles = acl.site_roles([identities.parse_edge("x=d")], shards=2)
    policies = {policy["id"]: policy["rules"] for policy in acl.policies("magnet", ["edge-x"], roles)}
    assert all(rule.startswith(("calibrator-ingress", "calibrator-egress")) for rule in policies["calibrator"])
    assert all(rule.startswith("calibrator-1-2-") for rule in policies["calibrator-1-2"])
    assert acl.password_roles(roles) == ["viewer", "edge-x"]


def test_the_trial_edge_role_declares_its_unhealthy_token_and_serves_its_status():
    rules = acl.rules("magnet")
    assert "magnet/@alive/device/*/unhealthy" in _keys(rules, "edge-ingress-liveliness_token")
    assert _keys(rules, "edge-ingress-declare_queryable+reply") == ["magnet/@status/edge-$*"]


def test_calibrator_identities_hold_only_their_shard_s_lease():
    rules = acl.rules("magnet", acl.site_roles(shards=3))
    assert "magnet/@lease/calibrator/0-1/**" in _keys(rules, "calibrator-ingress-liveliness_token")
    assert "magnet/@lease/calibrator/2-3/**" in _keys(rules, "calibrator-2-3-ingress-liveliness_token")
    leases = [k for rule in rules for k in rule["key_exprs"] if "@lease" in k]
    assert "magnet/@lease/**" not in leases


@pytest.mark.parametrize(
    "text",
    ["barn", "barn=", "=imu-1", "bad/name=imu-1", "x-password=imu-1", "barn=imu/1", "barn=imu-*"],
)
def test_a_bad_edge_option_is_one_line(text, tmp_path, capsys):
    assert main(["certs", "--out", str(tmp_path / "s"), "--edge", text]) == 2
    err = capsys.readouterr().err
    assert len(err.strip().splitlines()) == 1 and "Traceback" not in err
    assert not (tmp_path / "s" / "ca.key").exists(), "nothing written"


def test_add_needs_the_site_and_keeps_what_is_there(tmp_path: Path, capsys):
    site = tmp_path / "s"
    assert main(["certs", "--out", str(site), "--add", "--edge", "a=d1"]) == 2
    assert "--add needs the site" in capsys.readouterr().err
    assert main(["certs", "--out", str(site), "--edge", "a=d1", "--shards", "2"]) == 0
    ca, cert = (site / "ca.crt").read_bytes(), (site / "edge-a.crt").read_bytes()
    assert main(["certs", "--out", str(site), "--add", "--edge", "a=d1,d2", "--edge", "b=d3"]) == 0
    assert (site / "ca.crt").read_bytes() == ca and (site / "edge-a.crt").read_bytes() == cert
    saved = json.loads((site / "site.json").read_text())
    assert saved["edges"] == {"a": ["d1", "d2"], "b": ["d3"]} and saved["shards"] == 2
    router = (site / "router.json5").read_text()
    assert "magnet/d2/raw" in router and "edge-b-certificate" in router and "calibrator-1-2" in router
    assert main(["certs", "--out", str(site), "--edge", "c=d4"]) == 2, "without --add nothing is overwritten"
    moved = ["certs", "--out", str(site), "--add", "--listen", "tls/10.0.0.5:7447", "--edge", "c=d4"]
    assert main(moved) == 2
    assert "made with --listen tls/127.0.0.1:7447" in capsys.readouterr().err, "the same listeners, or nothing"


def test_a_calibrator_refuses_a_shard_its_certificate_may_not_hold(tmp_path, capsys):
    site = tmp_path / "s"
    assert main(["certs", "--out", str(site), "--shards", "2"]) == 0
    assert identities.certificate_identity(site / "calibrator-1-2.json5") == "calibrator-1-2"
    assert identities.certificate_identity(None) is None
    assert identities.certificate_identity(tmp_path / "missing.json5") is None
    identities.check_calibrator_identity("calibrator-1-2", 1, 2)
    identities.check_calibrator_identity("calibrator", 0, 1)
    identities.check_calibrator_identity("compass", 1, 2)  # not a calibrator identity: not this check's business
    with pytest.raises(ValueError, match="give the config of calibrator-1-2"):
        identities.check_calibrator_identity("calibrator", 1, 2)
    with pytest.raises(ValueError, match="give the config of calibrator"):
        identities.check_calibrator_identity("calibrator-0-2", 0, 1)
    config = str(site / "calibrator.json5")
    assert main(["calibrator", "--config", config, "--shard", "1/2", "--db", str(tmp_path / "c.db")]) == 2
    err = capsys.readouterr().err
    assert "calibrator-1-2" in err and len(err.strip().splitlines()) == 1
