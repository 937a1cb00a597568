"""``magnet keys --out DIR --name NAME``: an Ed25519 key pair for signing calibration records.

Writes ``DIR/NAME.key`` (the private key, PKCS#8 PEM, mode 0600: give it to ``magnet calibrator --signing-key``)
and ``DIR/NAME.pub`` (the public key, mode 0644: give it to ``magnet compass --trust`` and ``magnet get --trust``).
Nothing existing is overwritten.
"""

from __future__ import annotations

import argparse
import re
from pathlib import Path

from magnet import signing
from services.security import pki

NAME = re.compile(r"[A-Za-z0-9][A-Za-z0-9_.-]{0,63}")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--out", type=Path, required=True, help="directory to write into (created if missing)")
    parser.add_argument("--name", required=True, help="file name of the pair: NAME.key and NAME.pub")


def run(args: argparse.Namespace) -> int:
    if not NAME.fullmatch(args.name):
        raise ValueError(f"--name {args.name!r} must be letters, digits, '.', '_' or '-' (a file name, no path)")
    args.out.mkdir(parents=True, exist_ok=True)
    private_path, public_path = args.out / f"{args.name}.key", args.out / f"{args.name}.pub"
    existing = [str(p) for p in (private_path, public_path) if p.exists()]
    if existing:
        raise ValueError(f"{', '.join(existing)} already exist(s): nothing written; choose another --name or --out")
    private_pem, public_pem = signing.new_key_pair()
    pki.write_file(private_path, private_pem, pki.PRIVATE_MODE)
    pki.write_file(public_path, public_pem, pki.PUBLIC_MODE)
    key_id = signing.key_id(signing.load_public_key(public_pem))
    print(
        f"magnet keys: {private_path} (private, for --signing-key) and {public_path} (public, for --trust), "
        f"key id {key_id}"
    )
    return 0
