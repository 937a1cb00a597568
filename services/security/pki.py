"""A site certificate authority and one X.509 v3 certificate per role, with ``cryptography``.

Zenoh 1.10 (rustls/webpki) refuses version 1 certificates (``UnsupportedCertVersion``): every certificate here is v3
with ``basicConstraints`` (CA:TRUE only for the CA), ``keyUsage``, ``extendedKeyUsage`` (serverAuth for the router,
clientAuth for everyone) and a ``subjectAltName`` naming the hosts a client dials (default DNS localhost and IP
127.0.0.1). The common name is the role: the router's access-control subjects match it (``cert_common_names``).
Keys are ECDSA P-256, written as PKCS#8 PEM with mode 0600; certificates as PEM with mode 0644.
"""

from __future__ import annotations

import dataclasses
import datetime
import ipaddress
import os
from collections.abc import Sequence
from pathlib import Path

from cryptography import x509
from cryptography.hazmat.primitives import hashes, serialization
from cryptography.hazmat.primitives.asymmetric import ec
from cryptography.x509.oid import ExtendedKeyUsageOID, NameOID

CA_NAME = "magnet-ca"
PRIVATE_MODE = 0o600
PUBLIC_MODE = 0o644


@dataclasses.dataclass(frozen=True)
class Issued:
    """A certificate and its private key (PEM bytes)."""

    certificate_pem: bytes
    key_pem: bytes


def _new_key() -> ec.EllipticCurvePrivateKey:
    return ec.generate_private_key(ec.SECP256R1())


def _key_pem(key: ec.EllipticCurvePrivateKey) -> bytes:
    return key.private_bytes(
        serialization.Encoding.PEM, serialization.PrivateFormat.PKCS8, serialization.NoEncryption()
    )


def _names(dns: Sequence[str], ips: Sequence[str]) -> x509.SubjectAlternativeName:
    """subjectAltName of DNS names and IP addresses; ValueError naming a bad address."""
    entries: list[x509.GeneralName] = [x509.DNSName(name) for name in dns]
    for ip in ips:
        try:
            entries.append(x509.IPAddress(ipaddress.ip_address(ip)))
        except ValueError:
            raise ValueError(f"--ip {ip!r} is not an IP address") from None
    return x509.SubjectAlternativeName(entries)


def _builder(subject: str, issuer: x509.Name, public_key, days: int, now: datetime.datetime) -> x509.CertificateBuilder:
    return (
        x509.CertificateBuilder()
        .subject_name(x509.Name([x509.NameAttribute(NameOID.COMMON_NAME, subject)]))
        .issuer_name(issuer)
        .public_key(public_key)
        .serial_number(x509.random_serial_number())
        .not_valid_before(now - datetime.timedelta(minutes=5))
        .not_valid_after(now + datetime.timedelta(days=days))
        .add_extension(x509.SubjectKeyIdentifier.from_public_key(public_key), critical=False)
    )


def make_ca(days: int = 3650, name: str = CA_NAME) -> Issued:
    """A self-signed v3 CA certificate (basicConstraints CA:TRUE, pathlen 0; keyCertSign, cRLSign)."""
    key = _new_key()
    now = datetime.datetime.now(datetime.UTC)
    subject = x509.Name([x509.NameAttribute(NameOID.COMMON_NAME, name)])
    cert = (
        _builder(name, subject, key.public_key(), days, now)
        .add_extension(x509.BasicConstraints(ca=True, path_length=0), critical=True)
        .add_extension(
            x509.KeyUsage(
                digital_signature=False,
                content_commitment=False,
                key_encipherment=False,
                data_encipherment=False,
                key_agreement=False,
                key_cert_sign=True,
                crl_sign=True,
                encipher_only=False,
                decipher_only=False,
            ),
            critical=True,
        )
        .sign(key, hashes.SHA256())
    )
    return Issued(cert.public_bytes(serialization.Encoding.PEM), _key_pem(key))


def issue(
    ca: Issued,
    common_name: str,
    *,
    server: bool,
    dns: Sequence[str] = ("localhost",),
    ips: Sequence[str] = ("127.0.0.1",),
    days: int = 825,
) -> Issued:
    """A v3 end-entity certificate for ``common_name`` signed by ``ca``: clientAuth, plus serverAuth when
    ``server`` (the router, which other routers may also dial); subjectAltName from ``dns`` and ``ips``."""
    ca_cert = x509.load_pem_x509_certificate(ca.certificate_pem)
    ca_key = serialization.load_pem_private_key(ca.key_pem, password=None)
    ca_public = ca_cert.public_key()
    if not isinstance(ca_key, ec.EllipticCurvePrivateKey) or not isinstance(ca_public, ec.EllipticCurvePublicKey):
        raise ValueError("the CA's key is not an elliptic-curve key: make the CA with magnet's certificate command")
    key = _new_key()
    usages = [ExtendedKeyUsageOID.CLIENT_AUTH] + ([ExtendedKeyUsageOID.SERVER_AUTH] if server else [])
    now = datetime.datetime.now(datetime.UTC)
    cert = (
        _builder(common_name, ca_cert.subject, key.public_key(), days, now)
        .add_extension(x509.BasicConstraints(ca=False, path_length=None), critical=True)
        .add_extension(
            x509.KeyUsage(
                digital_signature=True,
                content_commitment=False,
                key_encipherment=False,
                data_encipherment=False,
                key_agreement=False,
                key_cert_sign=False,
                crl_sign=False,
                encipher_only=False,
                decipher_only=False,
            ),
            critical=True,
        )
        .add_extension(x509.ExtendedKeyUsage(usages), critical=False)
        .add_extension(_names(dns, ips), critical=False)
        .add_extension(x509.AuthorityKeyIdentifier.from_issuer_public_key(ca_public), critical=False)
        .sign(ca_key, hashes.SHA256())
    )
    return Issued(cert.public_bytes(serialization.Encoding.PEM), _key_pem(key))


def load(cert_path: Path, key_path: Path) -> Issued:
    """An existing certificate and key from PEM files (OSError when missing)."""
    return Issued(cert_path.read_bytes(), key_path.read_bytes())


def write_file(path: Path, data: bytes, mode: int) -> None:
    """Write ``data`` to a new file ``path`` with ``mode`` (FileExistsError when it exists: nothing is overwritten)."""
    fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL, mode)
    with os.fdopen(fd, "wb") as handle:
        handle.write(data)
    os.chmod(path, mode)  # the umask may have narrowed it


def write_issued(directory: Path, name: str, issued: Issued) -> None:
    """``directory/name.crt`` (0644) and ``directory/name.key`` (0600)."""
    write_file(directory / f"{name}.crt", issued.certificate_pem, PUBLIC_MODE)
    write_file(directory / f"{name}.key", issued.key_pem, PRIVATE_MODE)
