"""Ed25519 signatures on calibration records, end to end from the calibrator that made a record to every compass.

The signed bytes are the record's canonical form (``canonical_bytes``): the published map without its ``sig`` and
``key_id`` fields, as JSON with sorted keys, no spaces, and every whole-valued float written as an integer (a record
read back from the store or the wire may carry 50.0 where it was made with 50; both mean the same). ``sig`` is the
base64 signature, ``key_id`` the first 16 hex digits of the SHA-256 of the raw 32-byte public key.

Keys are PEM: the private key PKCS#8 (``NAME.key``), the public key SubjectPublicKeyInfo (``NAME.pub``). Pure: no
files here; the services read them.
"""

from __future__ import annotations

import base64
import binascii
import dataclasses
import json
import math
from collections.abc import Iterable, Mapping
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:  # cryptography is imported where a key is used: a compass with no trusted keys never loads it
    from cryptography.hazmat.primitives.asymmetric.ed25519 import Ed25519PrivateKey, Ed25519PublicKey

SIGNATURE_FIELDS = ("sig", "key_id")
KEY_ID_HEX = 16
SIGNATURE_B64_LEN = 88  # 64 bytes


class SignatureError(ValueError):
    """A record that cannot be trusted; ``cause`` is one word (unsigned, unknown-key, bad-signature)."""

    def __init__(self, cause: str, message: str) -> None:
        super().__init__(message)
        self.cause = cause


def _canonical(value: Any) -> Any:
    if isinstance(value, Mapping):
        return {str(k): _canonical(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_canonical(v) for v in value]
    if isinstance(value, float):
        if not math.isfinite(value):
            raise ValueError("a signed record holds only finite numbers")
        return int(value) if value.is_integer() and abs(value) < 2**63 else value
    return value


def canonical_bytes(record: Mapping[str, Any]) -> bytes:
    """The bytes signed for ``record``: without ``sig``/``key_id``, canonical JSON (see the module docstring)."""
    content = {k: v for k, v in record.items() if k not in SIGNATURE_FIELDS}
    return json.dumps(
        _canonical(content), sort_keys=True, separators=(",", ":"), ensure_ascii=False, allow_nan=False
    ).encode()


def key_id(public_key: Ed25519PublicKey) -> str:
    import hashlib

    from cryptography.hazmat.primitives import serialization

    raw = public_key.public_bytes(serialization.Encoding.Raw, serialization.PublicFormat.Raw)
    return hashlib.sha256(raw).hexdigest()[:KEY_ID_HEX]


def new_key_pair() -> tuple[bytes, bytes]:
    """A new key pair as PEM: (private PKCS#8, public SubjectPublicKeyInfo)."""
    from cryptography.hazmat.primitives import serialization
    from cryptography.hazmat.primitives.asymmetric.ed25519 import Ed25519PrivateKey

    private = Ed25519PrivateKey.generate()
    private_pem = private.private_bytes(
        serialization.Encoding.PEM, serialization.PrivateFormat.PKCS8, serialization.NoEncryption()
    )
    public_pem = private.public_key().public_bytes(
        serialization.Encoding.PEM, serialization.PublicFormat.SubjectPublicKeyInfo
    )
    return private_pem, public_pem


def load_private_key(pem: bytes, name: str = "the signing key") -> Ed25519PrivateKey:
    """An Ed25519 private key from PEM; ValueError naming ``name`` when it is not one."""
    from cryptography.hazmat.primitives import serialization
    from cryptography.hazmat.primitives.asymmetric.ed25519 import Ed25519PrivateKey

    try:
        key = serialization.load_pem_private_key(pem, password=None)
    except (ValueError, TypeError) as exc:
        raise ValueError(f"{name} is not a PEM private key ({exc}): make one with `magnet keys`") from None
    if not isinstance(key, Ed25519PrivateKey):
        raise ValueError(f"{name} is not an Ed25519 key: make one with `magnet keys`")
    return key


def load_public_key(pem: bytes, name: str = "the trusted key") -> Ed25519PublicKey:
    """An Ed25519 public key from PEM; ValueError naming ``name`` when it is not one."""
    from cryptography.hazmat.primitives import serialization
    from cryptography.hazmat.primitives.asymmetric.ed25519 import Ed25519PublicKey

    try:
        key = serialization.load_pem_public_key(pem)
    except (ValueError, TypeError) as exc:
        raise ValueError(f"{name} is not a PEM public key ({exc}): give the .pub file `magnet keys` wrote") from None
    if not isinstance(key, Ed25519PublicKey):
        raise ValueError(f"{name} is not an Ed25519 public key: give the .pub file `magnet keys` wrote")
    return key


@dataclasses.dataclass(frozen=True)
class Signer:
    """Signs records with one private key."""

    private_key: Ed25519PrivateKey

    @property
    def key_id(self) -> str:
        return key_id(self.private_key.public_key())

    def sign(self, record: Mapping[str, Any]) -> dict[str, Any]:
        """A copy of ``record`` with ``sig`` and ``key_id`` (any earlier signature replaced)."""
        signature = self.private_key.sign(canonical_bytes(record))
        content = {k: v for k, v in record.items() if k not in SIGNATURE_FIELDS}
        return {**content, "sig": base64.b64encode(signature).decode(), "key_id": self.key_id}


class TrustedKeys:
    """The public keys a verifier trusts, by key id. Empty: nothing is checked (``enabled`` is False)."""

    def __init__(self, keys: Iterable[Ed25519PublicKey] = ()) -> None:
        self._keys = {key_id(key): key for key in keys}

    @property
    def enabled(self) -> bool:
        return bool(self._keys)

    @property
    def key_ids(self) -> list[str]:
        return sorted(self._keys)

    def verify(self, record: Mapping[str, Any]) -> str:
        """The key id that signed ``record``; SignatureError when it is unsigned, signed by a key not trusted, or the
        signature does not match its content."""
        sig, kid = record.get("sig"), record.get("key_id")
        if not sig or not kid:
            raise SignatureError("unsigned", "the record is not signed and signed records are required")
        if not isinstance(sig, str) or not isinstance(kid, str) or len(sig) != SIGNATURE_B64_LEN:
            raise SignatureError("bad-signature", "the record's sig/key_id fields are malformed")
        key = self._keys.get(kid)
        if key is None:
            raise SignatureError("unknown-key", f"the record is signed by key {kid[:KEY_ID_HEX]}, which is not trusted")
        from cryptography.exceptions import InvalidSignature

        try:
            key.verify(base64.b64decode(sig, validate=True), canonical_bytes(record))
        except (InvalidSignature, binascii.Error, ValueError):
            raise SignatureError("bad-signature", f"the signature of key {kid} does not match the record") from None
        return kid
