"""The calibrator's side of trust (docs/trust.md): a record is signed once, when it is made; read back from the store
it is served as stored, and the ones this calibrator's key does not verify are found and logged. No zenoh inside."""

from __future__ import annotations

import dataclasses
import logging
from collections.abc import Mapping

from magnet import signing, wire
from magnet.model import Calibration

log = logging.getLogger("magnet.calibrator")


def new_record(
    signer: signing.Signer | None, device: str, created_ns: int, calibration: Calibration, version: int
) -> wire.DeviceCalibration:
    """A new record, signed with ``signer`` (unsigned without one). The only place a record is signed: when it is
    made (fit, session commit, rollback), never when it is read back."""
    record = wire.DeviceCalibration(device, created_ns, calibration, version=version)
    if signer is None:
        return record
    signed = signer.sign(record.to_record())
    return dataclasses.replace(record, sig=signed["sig"], key_id=signed["key_id"])


def made_by(signer: signing.Signer | None, record: wire.DeviceCalibration) -> bool:
    """Whether ``record`` verifies under ``signer``'s own public key (always True without a key)."""
    if signer is None:
        return True
    try:
        signing.TrustedKeys([signer.private_key.public_key()]).verify(record.to_record())
    except signing.SignatureError:
        return False
    return True


def unverified(
    signer: signing.Signer,
    in_force: Mapping[str, wire.DeviceCalibration],
    previous: Mapping[str, wire.DeviceCalibration],
    previously_unverified: set[str],
) -> set[str]:
    """The devices of ``in_force`` whose record ``signer``'s key does not verify (unsigned rows from before the key,
    rows written into the file by someone else), logged. A record equal to the one ``previous`` held and verified is
    not checked again (a takeover re-checks only what changed since the last read)."""

    def verified(device: str, record: wire.DeviceCalibration) -> bool:
        old = previous.get(device)
        if old is not None and device not in previously_unverified and old.to_record() == record.to_record():
            return True
        return made_by(signer, record)

    found = {d for d, r in in_force.items() if not verified(d, r)}
    if found:
        log.warning(
            "%d calibration(s) in force are not signed by this calibrator's key %s and are served as stored "
            "(compasses with --trust refuse them; recalibrate or roll back to a signed one): %s",
            len(found),
            signer.key_id,
            ", ".join(f"{d} ({in_force[d].id})" for d in sorted(found)[:20]),
        )
    return found
