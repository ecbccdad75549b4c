"""Signed certificates: Ed25519 signatures with a key of the user's (optional extra ``simgap[sign]``).

A certificate's sha256 digest detects accidents (a truncated or edited file), not forgery:
whoever edits the file can recompute the digest. Users who exchange certificates can sign them:

* ``simgap key new --out KEY`` writes a private key ``KEY`` (PEM, mode 0600) and ``KEY.pub``;
* with ``SIMGAP_SIGNING_KEY=KEY`` (or ``certify --sign-key KEY``) every certificate written is
  signed: ``signature = {alg: ed25519, public_key: hex, value: hex}`` over its digest;
* with ``SIMGAP_TRUSTED_KEYS=A.pub:B.pub`` every certificate read must carry a valid signature by
  one of those keys; an unsigned, otherwise-signed or forged one is refused.

The cryptography is the ``cryptography`` package's (no hand-rolled code here).
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Optional

from .errors import SimgapError

KEY_ENV = "SIMGAP_SIGNING_KEY"
TRUST_ENV = "SIMGAP_TRUSTED_KEYS"
ALG = "ed25519"


def _ed25519():
    try:
        from cryptography.hazmat.primitives.asymmetric import ed25519
    except ImportError:
        from .paths import install_command
        raise SimgapError(f"signing needs the cryptography package: {install_command('sign')}") from None
    return ed25519


def _serialization():
    from cryptography.hazmat.primitives import serialization
    return serialization


def new_key(path) -> tuple[Path, Path]:
    """Write a new private key to ``path`` (PEM, readable by the owner only) and its public key to
    ``path.pub``; refuse to overwrite either."""
    ed, ser = _ed25519(), _serialization()
    path = Path(path)
    pub = path.with_name(path.name + ".pub")
    for p in (path, pub):
        if p.exists():
            raise SimgapError(f"{str(p)!r} exists; a key is never overwritten (choose another name)")
    key = ed.Ed25519PrivateKey.generate()
    priv = key.private_bytes(ser.Encoding.PEM, ser.PrivateFormat.PKCS8, ser.NoEncryption())
    fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600)
    with os.fdopen(fd, "wb") as fh:
        fh.write(priv)
    pub.write_bytes(key.public_key().public_bytes(ser.Encoding.PEM, ser.PublicFormat.SubjectPublicKeyInfo))
    return path, pub


def _raw_public(key) -> str:
    ser = _serialization()
    return key.public_bytes(ser.Encoding.Raw, ser.PublicFormat.Raw).hex()


def _load_private(path):
    ed, ser = _ed25519(), _serialization()
    try:
        key = ser.load_pem_private_key(Path(path).read_bytes(), password=None)
    except (OSError, ValueError, TypeError) as e:
        raise SimgapError(f"signing key {str(path)!r} is not readable as a PEM private key ({e})") from None
    if not isinstance(key, ed.Ed25519PrivateKey):
        raise SimgapError(f"signing key {str(path)!r} is not an Ed25519 key (make one with: simgap key new)")
    return key


def _load_public(path):
    ed, ser = _ed25519(), _serialization()
    try:
        key = ser.load_pem_public_key(Path(path).read_bytes())
    except (OSError, ValueError, TypeError) as e:
        raise SimgapError(f"trusted key {str(path)!r} is not readable as a PEM public key ({e})") from None
    if not isinstance(key, ed.Ed25519PublicKey):
        raise SimgapError(f"trusted key {str(path)!r} is not an Ed25519 public key")
    return key


def signing_key(explicit: Optional[str] = None) -> Optional[str]:
    """The private key to sign with: ``explicit`` (a command-line flag), else $SIMGAP_SIGNING_KEY."""
    return explicit or os.environ.get(KEY_ENV) or None


def sign(digest: str, key_path) -> dict:
    """The signature entry of a file whose content digest is ``digest``."""
    key = _load_private(key_path)
    return {"alg": ALG, "public_key": _raw_public(key.public_key()), "value": key.sign(digest.encode()).hex()}


def trusted_keys() -> list:
    """Public keys named by $SIMGAP_TRUSTED_KEYS (paths separated by ':'); empty: no check."""
    return [_load_public(p) for p in os.environ.get(TRUST_ENV, "").split(os.pathsep) if p.strip()]


def check(d: dict, source: str) -> None:
    """With trusted keys configured, refuse ``d`` (a file's JSON, digest verified) unless its
    signature is a valid one by a trusted key over its digest."""
    keys = trusted_keys()
    if not keys:
        return
    sig = d.get("signature")
    if not isinstance(sig, dict) or sig.get("alg") != ALG:
        raise SimgapError(f"{source} is not signed, and {TRUST_ENV} asks for a signature by a trusted key (refused)")
    match = [k for k in keys if _raw_public(k) == sig.get("public_key")]
    if not match:
        raise SimgapError(f"{source} is signed by a key that is not among {TRUST_ENV} (refused)")
    from cryptography.exceptions import InvalidSignature
    try:
        match[0].verify(bytes.fromhex(str(sig.get("value"))), str(d.get("digest")).encode())
    except (InvalidSignature, ValueError):
        raise SimgapError(f"{source}: its signature does not match its content: forged or edited after signing "
                          "(refused)") from None
