"""``twin security init``: a lab's CA, a certificate per identity, and the Zenoh configs that use them.

The ``cryptography`` package makes the keys (ECDSA P-256) and certificates:
no hand-rolled crypto and no openssl subprocess whose version and flags vary
by host. Run it again with more ``--device`` to add devices: the CA and the
certificates already there are kept (the CA key lives in ``private/``; keep
that folder off the lab's machines once the certificates are issued).
"""

from __future__ import annotations

import datetime
import ipaddress
import json
import os
from collections.abc import Callable
from pathlib import Path

from cryptography import x509
from cryptography.hazmat.primitives import hashes, serialization
from cryptography.hazmat.primitives.asymmetric import ec
from cryptography.x509.oid import ExtendedKeyUsageOID, NameOID

from twin.core.bus.security import MANIFEST, Identity, router_config, session_config
from twin.core.errors import TwinError
from twin.core.whole_files import locked, written_whole

_NAME_OK = set("abcdefghijklmnopqrstuvwxyzABCDEFGHIJKLMNOPQRSTUVWXYZ0123456789_-")


def init(root: str | Path, lab: str, devices: list[str], hosts: list[str] | None = None,
         days: int = 365, endpoint: str = "tls/127.0.0.1:7447",
         on_wait: Callable[[], None] = lambda: None) -> list[Path]:
    """Create or extend the security directory ``root`` of ``lab``; returns the files written. One at a time: two
    started together on a new directory (a device each) each made a CA, and the first one's certificates were then
    signed by a CA no longer on disk; the second waits (``on_wait`` says so), then extends what the first made."""
    root = Path(root)
    hosts = list(hosts or []) or ["localhost", "127.0.0.1"]
    for name in [lab, *devices]:
        if not name or len(name) > 64 or not set(name) <= _NAME_OK:
            raise TwinError(f"{name!r}: lab and device names are 1-64 letters, digits, '_' or '-'")
    root.mkdir(parents=True, exist_ok=True)
    with locked(root / ".init.lock", "", on_wait=on_wait):
        return _init(root, lab, devices, hosts, days, endpoint)


def _init(root: Path, lab: str, devices: list[str], hosts: list[str], days: int, endpoint: str) -> list[Path]:
    old = _read_manifest(root)
    if old and old.get("lab") != lab:
        raise TwinError(f"{root} holds the certificates of lab {old.get('lab')!r}: use another directory for {lab!r}")
    devices = sorted(set(devices) | set(old.get("devices") or []))
    written: list[Path] = []
    (root / "private").mkdir(parents=True, exist_ok=True)
    os.chmod(root / "private", 0o700)
    ca_key, ca_cert = _ca(root, lab, days, written)
    people = [Identity("router", lab), Identity("orchestrator", lab), Identity("scheduler", lab),
              Identity("watcher", lab), Identity("operator", lab)] + [Identity("device", lab, d) for d in devices]
    for who in people:
        folder = who.folder(root)
        if (folder / "cert.pem").is_file() and (folder / "key.pem").is_file():
            continue
        folder.mkdir(parents=True, exist_ok=True)
        key = ec.generate_private_key(ec.SECP256R1())
        cert = _issue(ca_key, ca_cert, who.common_name, hosts if who.role == "router" else [], days, key)
        written += [_write_key(folder / "key.pem", key), _write(folder / "cert.pem", _pem(cert))]
    manifest = {"lab": lab, "devices": devices, "router_hosts": hosts, "endpoint": endpoint,
                "identities": {str(w) or w.role: w.common_name for w in people}}
    written.append(_write(root / MANIFEST, json.dumps(manifest, indent=2).encode()))
    written.append(_write(root / "router.json5", _json5({"mode": "router", "listen": {"endpoints": [endpoint]},
                                                         **_nested(router_config(root, lab))})))
    for who in people[1:]:
        client = {"mode": "client", "connect": {"endpoints": [endpoint]},
                  "scouting": {"multicast": {"enabled": False}}, **_nested(session_config(root, who))}
        written.append(_write(who.folder(root) / "zenoh.json5", _json5(client)))
    return written


def _read_manifest(root: Path) -> dict:
    try:
        return json.loads((root / MANIFEST).read_text())
    except (OSError, ValueError):
        return {}


def _ca(root: Path, lab: str, days: int, written: list[Path]) -> tuple[ec.EllipticCurvePrivateKey, x509.Certificate]:
    key_path, cert_path = root / "private" / "ca.key", root / "ca.pem"
    if key_path.is_file() and cert_path.is_file():
        key = serialization.load_pem_private_key(key_path.read_bytes(), password=None)
        return key, x509.load_pem_x509_certificate(cert_path.read_bytes())
    key = ec.generate_private_key(ec.SECP256R1())
    name = x509.Name([x509.NameAttribute(NameOID.COMMON_NAME, f"labtwin CA of lab {lab}")])
    now = datetime.datetime.now(datetime.timezone.utc)
    cert = (x509.CertificateBuilder().subject_name(name).issuer_name(name).public_key(key.public_key())
            .serial_number(x509.random_serial_number()).not_valid_before(now - datetime.timedelta(minutes=5))
            .not_valid_after(now + datetime.timedelta(days=days))
            .add_extension(x509.BasicConstraints(ca=True, path_length=0), critical=True)
            .add_extension(x509.KeyUsage(digital_signature=True, key_cert_sign=True, crl_sign=True,
                                         content_commitment=False, key_encipherment=False, data_encipherment=False,
                                         key_agreement=False, encipher_only=False, decipher_only=False), critical=True)
            .add_extension(x509.SubjectKeyIdentifier.from_public_key(key.public_key()), critical=False)
            .sign(key, hashes.SHA256()))
    written += [_write_key(key_path, key), _write(cert_path, _pem(cert))]
    return key, cert


def _issue(ca_key: ec.EllipticCurvePrivateKey, ca_cert: x509.Certificate, common_name: str, hosts: list[str],
           days: int, key: ec.EllipticCurvePrivateKey) -> x509.Certificate:
    now = datetime.datetime.now(datetime.timezone.utc)
    b = (x509.CertificateBuilder().subject_name(x509.Name([x509.NameAttribute(NameOID.COMMON_NAME, common_name)]))
         .issuer_name(ca_cert.subject).public_key(key.public_key()).serial_number(x509.random_serial_number())
         .not_valid_before(now - datetime.timedelta(minutes=5)).not_valid_after(now + datetime.timedelta(days=days))
         .add_extension(x509.BasicConstraints(ca=False, path_length=None), critical=True)
         .add_extension(x509.ExtendedKeyUsage([ExtendedKeyUsageOID.SERVER_AUTH, ExtendedKeyUsageOID.CLIENT_AUTH]),
                        critical=False)
         .add_extension(x509.AuthorityKeyIdentifier.from_issuer_public_key(ca_key.public_key()), critical=False))
    if hosts:
        names: list[x509.GeneralName] = []
        for h in hosts:
            try:
                names.append(x509.IPAddress(ipaddress.ip_address(h)))
            except ValueError:
                names.append(x509.DNSName(h))
        b = b.add_extension(x509.SubjectAlternativeName(names), critical=False)
    return b.sign(ca_key, hashes.SHA256())


def _pem(cert: x509.Certificate) -> bytes:
    return cert.public_bytes(serialization.Encoding.PEM)


def _write(path: Path, data: bytes) -> Path:
    with written_whole(path) as partial:  # a router re-reads the manifest while it runs: never half of one
        partial.write_bytes(data)
    return path


def _write_key(path: Path, key: ec.EllipticCurvePrivateKey) -> Path:
    data = key.private_bytes(serialization.Encoding.PEM, serialization.PrivateFormat.PKCS8,
                             serialization.NoEncryption())
    fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
    with os.fdopen(fd, "wb") as f:
        f.write(data)
    return path


def _nested(paths: dict[str, object]) -> dict[str, object]:
    """``{"a/b/c": 1}`` → ``{"a": {"b": {"c": 1}}}`` (a Zenoh config file's shape)."""
    out: dict[str, object] = {}
    for path, value in paths.items():
        node = out
        *parents, leaf = path.split("/")
        for p in parents:
            node = node.setdefault(p, {})  # type: ignore[assignment]
        node[leaf] = value
    return out


def _json5(data: dict) -> bytes:
    return (json.dumps(data, indent=2) + "\n").encode()  # JSON is JSON5
