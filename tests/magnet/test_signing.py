"""Signed calibrations: magnet.signing, `magnet keys`, the calibrator's signature and what the compass applies."""

from __future__ import annotations

import json

import msgpack
import numpy as np
import pytest
from compass_steps import compass_core

from magnet import signing, wire
from magnet.earth.expected import Earth
from magnet.model import Calibration
from services.calibrator.service import Calibrator, CalibratorSettings
from services.calibrator.store import CalibrationStore
from services.cli import main

GENUINE = Calibration(
    "ellipsoid",
    [10.0, -5.0, 2.0],
    np.diag([1.05, 0.95, 1.0]),
    field_strength=50,
    quality={"coverage": 0.9, "expected_field_ut": 50},
)
KEY = "magnet/k/calibration"


def _pair():
    private_pem, public_pem = signing.new_key_pair()
    return signing.Signer(signing.load_private_key(private_pem)), signing.load_public_key(public_pem)


@pytest.fixture(scope="module")
def keys():
    return _pair(), _pair()  # the calibrator's key, and another one


def _signed(signer, calibration=GENUINE, created_ns=10, device="k"):
    return signer.sign(wire.calibration_record(device, calibration, created_ns))


def test_a_signed_record_verifies_after_the_wire_and_the_store(keys, tmp_path):
    (signer, public), (_, other) = keys
    trusted = signing.TrustedKeys([public])
    record = _signed(signer)
    assert trusted.verify(record) == signer.key_id
    # the wire (msgpack) and the store (JSON) give back a record that still verifies, re-rendered from its type
    over_wire = wire.decode_calibration(msgpack.packb(record))
    assert trusted.verify(over_wire.to_record()) == signer.key_id
    with CalibrationStore(tmp_path / "c.db") as store:
        store.save(over_wire)
        assert trusted.verify(store.latest("k").to_record()) == signer.key_id
    # 50 and 50.0 mean the same: the canonical bytes agree
    assert signing.canonical_bytes({"a": 50}) == signing.canonical_bytes({"a": 50.0})
    with pytest.raises(signing.SignatureError) as refused:
        signing.TrustedKeys([other]).verify(record)
    assert refused.value.cause == "unknown-key"


@pytest.mark.parametrize(
    "change, cause",
    [
        ({"offset": [100.0, 0.0, 0.0]}, "bad-signature"),
        ({"device": "j"}, "bad-signature"),
        ({"sig": None, "key_id": None}, "unsigned"),
        ({"sig": "A" * 88}, "bad-signature"),
        ({"sig": "not base64!"}, "bad-signature"),
    ],
)
def test_a_changed_or_unsigned_record_is_refused(keys, change, cause):
    (signer, public), _ = keys
    with pytest.raises(signing.SignatureError) as refused:
        signing.TrustedKeys([public]).verify({**_signed(signer), **change})
    assert refused.value.cause == cause


def test_keys_command_writes_a_private_key_0600_and_a_public_key_0644(tmp_path, capsys):
    assert main(["keys", "--out", str(tmp_path / "k"), "--name", "calibrator"]) == 0
    private, public = tmp_path / "k/calibrator.key", tmp_path / "k/calibrator.pub"
    assert private.stat().st_mode & 0o777 == 0o600 and public.stat().st_mode & 0o777 == 0o644
    signer = signing.Signer(signing.load_private_key(private.read_bytes()))
    assert signer.key_id in capsys.readouterr().out
    assert signing.TrustedKeys([signing.load_public_key(public.read_bytes())]).verify(_signed(signer))
    assert main(["keys", "--out", str(tmp_path / "k"), "--name", "calibrator"]) == 2, "nothing is overwritten"
    assert "already exist" in capsys.readouterr().err
    assert main(["keys", "--out", str(tmp_path / "k"), "--name", "../evil"]) == 2
    with pytest.raises(ValueError, match=r"not an Ed25519 public key|not a PEM public key"):
        signing.load_public_key(private.read_bytes(), "x.pub")


def test_the_calibrator_signs_a_record_when_it_makes_it_and_never_when_it_reads_it(keys, tmp_path):
    (signer, public), _ = keys
    trusted = signing.TrustedKeys([public])
    published = []
    with CalibrationStore(tmp_path / "c.db") as store:
        unsigned_before = wire.DeviceCalibration("old", 1, GENUINE)
        store.save(unsigned_before)  # stored before the calibrator had a key (or written by someone else)
        calibrator = Calibrator(
            store, CalibratorSettings(), lambda kind, dev, payload: published.append(payload), signer=signer
        )
        assert calibrator.records.in_force["old"].sig == "", "served as stored: not signed on the way out"
        assert calibrator.status("c").counters.unverified_records == 1
        with pytest.raises(signing.SignatureError):
            trusted.verify(calibrator.records.in_force["old"].to_record())
        record = calibrator.commit("k", GENUINE)
        assert trusted.verify(record.to_record()) and trusted.verify(wire.unpack(published[0]))
        assert store.latest("k").sig == record.sig, "stored with its signature"
        assert record.version == 1 and wire.unpack(published[0])["version"] == 1
        again = Calibrator(store, CalibratorSettings(), lambda *a: None, signer=signer)
        assert again.records.in_force["k"].sig == record.sig and trusted.verify(again.records.in_force["k"].to_record())
        assert again.status("c").counters.unverified_records == 1, "only the old unsigned row"


def test_a_row_written_into_the_store_by_hand_is_served_unsigned_and_refused_by_trusting_compasses(keys, tmp_path):
    (signer, public), _ = keys
    with CalibrationStore(tmp_path / "c.db") as store:
        calibrator = Calibrator(store, CalibratorSettings(), lambda *a: None, signer=signer)
        genuine = calibrator.commit("k", GENUINE)
        moved = GENUINE.replace(offset=np.array([100.0, 0.0, 0.0]))
        planted = wire.DeviceCalibration("k", 20, moved, version=genuine.version + 1).to_record()
        store._db.execute(
            "INSERT INTO calibrations (device, id, created_ns, record, version) VALUES (?, ?, ?, ?, ?)",
            ("k", planted["id"], 20, json.dumps(planted), planted["version"]),
        )
        restarted = Calibrator(store, CalibratorSettings(), lambda *a: None, signer=signer)
        served = restarted.records.in_force["k"]
    assert served.id == planted["id"] and served.sig == "", "served as stored, not signed by the calibrator"
    assert restarted.status("c").counters.unverified_records == 1
    compass = _compass([public])
    assert compass.accept_calibration(msgpack.packb(genuine.to_record()), KEY, "magnet")
    assert not compass.accept_calibration(msgpack.packb(served.to_record()), KEY, "magnet")
    assert compass.calibrations.in_force["k"].id == genuine.id and compass.drops.counts == {"calibration:unsigned": 1}


def _compass(trusted):
    return compass_core(Earth(), window=1, trusted=signing.TrustedKeys(trusted))


def test_compass_with_trusted_keys_applies_only_genuine_calibrations(keys):
    (signer, public), (other_signer, _) = keys
    compass = _compass([public])
    assert compass.accept_calibration(msgpack.packb(_signed(signer)), KEY, "magnet")
    genuine_id = compass.calibrations.in_force["k"].id
    moved = GENUINE.replace(offset=np.array([100.0, 0.0, 0.0]))
    reflection = GENUINE.replace(matrix=np.diag([-1.0, 1.0, 1.0]))
    hostile = {
        "forged": _signed(other_signer, moved, 20),
        "unsigned": wire.calibration_record("k", moved, 20),
        "tampered": {**_signed(signer, GENUINE, 20), "offset": [100.0, 0.0, 0.0]},
        "not accepted": _signed(signer, moved.replace(accepted=False), 20),
        "reflection": {**_signed(signer, GENUINE, 20), "matrix": reflection.matrix.tolist()},
        "1e9 scale": {**_signed(signer, GENUINE, 20), "matrix": (1e9 * np.eye(3)).tolist()},
        "older": _signed(signer, moved, 5),
    }
    for name, record in hostile.items():
        assert not compass.accept_calibration(msgpack.packb(record), KEY, "magnet"), name
        assert compass.calibrations.in_force["k"].id == genuine_id, f"{name}: the genuine calibration stays in force"
    assert compass.drops.counts == {
        "calibration:unknown-key": 1,
        "calibration:unsigned": 1,
        "calibration:bad-signature": 1,
        "calibration:not-accepted": 1,
        "calibration:bad-calibration": 2,
        "calibration:stale": 1,
    }
    assert set(compass.calibrations.refused) == {"k"}, "the calibrators are asked again for k"
    newer = _signed(signer, moved, 30)
    assert compass.accept_calibration(msgpack.packb(newer), KEY, "magnet") and compass.calibrations.in_force["k"].sig


def test_compass_without_trusted_keys_applies_unsigned_but_never_a_rejected_fit():
    compass = _compass([])
    assert compass.accept_calibration(wire.encode_calibration("k", GENUINE, 1), KEY, "magnet")
    rejected = wire.calibration_record("k", GENUINE.replace(offset=np.array([100.0, 0, 0]), accepted=False), 2)
    assert not compass.accept_calibration(msgpack.packb(rejected), KEY, "magnet")
    assert compass.calibrations.in_force["k"].id == GENUINE.content_id


def test_the_issue_s_forged_record_is_refused_even_without_keys():
    forged = {
        "v": 1,
        "device": "k-003",
        "offset": [100, 0, 0],
        "matrix": [[-1, 0, 0], [0, 1, 0], [0, 0, 1]],
        "accepted": False,
    }
    compass = _compass([])
    assert not compass.accept_calibration(msgpack.packb(forged), "magnet/k-003/calibration", "magnet")
    assert "k-003" not in compass.calibrations.in_force and set(compass.calibrations.refused) == {"k-003"}
    assert json.dumps(compass.status("c").to_dict())  # counted, JSON-able
