"""Who may say what on a lab's Zenoh bus: identities, their TLS files, and the router's access control.

``twin security init`` (``twin.tools.security_init``) writes a lab's security
directory: a CA, a certificate per identity, and a manifest. This module only
reads it: the TLS settings of a session for one identity, and the router's
config, whose access-control policy denies by default and allows

- a device: publishing on its own ``evt``/``telemetry`` keys, subscribing to
  its own ``cmd`` key, serving its own ``health`` key, declaring its own
  liveliness token, watching the orchestrator's token, and hearing the lab's
  clock (``labtwin/<lab>/clock``, which only the orchestrator may publish);
  claiming itself before it starts (``labtwin/<lab>/claim/dev/<id>/*``) and
  seeing another process's claim or token of the same device;
- the orchestrator: everything under ``labtwin/<lab>/`` (it is the lab);
- a scheduler agent: serving ``labtwin/<lab>/agent/scheduler/**``, hearing
  the lab's clock and watching the orchestrator's token; claiming the agent's
  part (``labtwin/<lab>/claim/agent/*``) and seeing another agent's;
- a watcher: reading (subscribing, watching tokens, paging the history);
- an operator: asking the campaign's control desk (``labtwin/<lab>/control/**``:
  ``twin ctl``), and nothing else.

Subjects are matched by certificate common name, which only mutual TLS
proves: the router requires a client certificate signed by the lab's CA.
"""

from __future__ import annotations

import ipaddress
import json
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from twin.core import keys
from twin.core.errors import BusError

MANIFEST = "labtwin-security.json"
_ALL = ["put", "delete", "declare_subscriber", "query", "reply", "declare_queryable", "liveliness_token",
        "liveliness_query", "declare_liveliness_subscriber"]


@dataclass(frozen=True)
class Identity:
    role: str
    lab: str
    name: str = ""  # a device's id

    @property
    def common_name(self) -> str:
        return f"{self.role}.{self.name}.{self.lab}" if self.name else f"{self.role}.{self.lab}"

    def folder(self, root: Path) -> Path:
        return root / "devices" / self.name if self.role == "device" else root / self.role

    def __str__(self) -> str:
        return f"{self.role} {self.name}".strip()


def manifest(root: str | Path, lab: str) -> dict[str, Any]:
    """The security directory's manifest, checked against the lab it is used for."""
    root = Path(root)
    path = root / MANIFEST
    try:
        data = json.loads(path.read_text())
    except FileNotFoundError:
        raise BusError(f"{root} is not a lab security directory (no {MANIFEST}): create one with "
                       f"`twin security init {root} --lab {lab} --device ID ...`") from None
    except (OSError, ValueError) as exc:
        raise BusError(f"{path} cannot be read ({exc}): create the directory again with twin security init") from None
    if data.get("lab") != lab:
        raise BusError(f"{root} was made for lab {data.get('lab')!r}, not {lab!r}: use that lab's directory, or "
                       f"`twin security init DIR --lab {lab}`")
    return data


def devices_of(root: str | Path, lab: str) -> frozenset[str]:
    """The devices a security directory has certificates for (its manifest's)."""
    return frozenset(manifest(root, lab).get("devices") or ())


def lab_of(root: str | Path) -> str:
    """The lab a security directory was made for."""
    try:
        return str(json.loads((Path(root) / MANIFEST).read_text())["lab"])
    except (OSError, ValueError, KeyError):
        raise BusError(f"{root} is not a lab security directory (no readable {MANIFEST}): create one with "
                       "`twin security init DIR --lab LAB --device ID ...`") from None


def files(root: str | Path, who: Identity) -> dict[str, Path]:
    """The CA certificate and ``who``'s certificate and key, which must exist."""
    root = Path(root).resolve()
    manifest(root, who.lab)
    folder = who.folder(root)
    found = {"ca": root / "ca.pem", "cert": folder / "cert.pem", "key": folder / "key.pem"}
    missing = [str(p) for p in found.values() if not p.is_file()]
    add = f" --device {who.name}" if who.role == "device" else ""
    if missing:
        raise BusError(f"no certificate for the {who} of lab {who.lab} in {root} ({', '.join(missing)} missing): "
                       f"add it with `twin security init {root} --lab {who.lab}{add}` (the CA is reused)")
    for what, path in found.items():
        why = _unusable(path, what)
        if why:
            again = (f"remove {root} and make them all again" if what == "ca" else
                     f"remove {folder} and make it again") + f" with `twin security init {root} --lab {who.lab}{add}`"
            raise BusError(f"{path}: {why}, so TLS would fail with Zenoh's words alone: {again}")
    return found


def _unusable(path: Path, what: str) -> str:
    """Why a PEM file of a security directory cannot serve ('' if it can): not a certificate or key (overwritten,
    cut short), or a certificate outside its dates."""
    import datetime

    from cryptography import x509
    from cryptography.hazmat.primitives import serialization

    data = path.read_bytes()[:1 << 20]
    try:
        if what == "key":
            serialization.load_pem_private_key(data, password=None)
            return ""
        cert = x509.load_pem_x509_certificate(data)
    except (ValueError, TypeError):
        return f"not a PEM {'private key' if what == 'key' else 'certificate'} (overwritten or cut short)"
    now = datetime.datetime.now(datetime.timezone.utc)
    if cert.not_valid_after_utc < now:
        return f"the certificate expired on {cert.not_valid_after_utc:%Y-%m-%d %H:%M} UTC"
    if cert.not_valid_before_utc > now:
        return (f"the certificate is valid only from {cert.not_valid_before_utc:%Y-%m-%d %H:%M} UTC: this machine's "
                "clock is behind the one that made it")
    return ""


def session_config(root: str | Path, who: Identity) -> dict[str, Any]:
    """Zenoh config paths for a client session of ``who``: TLS with its certificate (mutual TLS)."""
    f = files(root, who)
    tls = "transport/link/tls/"
    return {tls + "root_ca_certificate": str(f["ca"]), tls + "connect_certificate": str(f["cert"]),
            tls + "connect_private_key": str(f["key"]), tls + "enable_mtls": True}


def router_config(root: str | Path, lab: str) -> dict[str, Any]:
    """Zenoh config paths for the lab's router: TLS listener, client certificates required, access control."""
    root = Path(root).resolve()
    data = manifest(root, lab)
    f = files(root, Identity("router", lab))
    tls = "transport/link/tls/"
    return {tls + "root_ca_certificate": str(f["ca"]), tls + "listen_certificate": str(f["cert"]),
            tls + "listen_private_key": str(f["key"]), tls + "enable_mtls": True,
            "access_control": access_control(lab, list(data.get("devices") or []))}


def access_control(lab: str, devices: list[str]) -> dict[str, Any]:
    """The router's policy: deny by default; each identity allowed only its own keys (see the module doc)."""
    p = f"{keys.PREFIX}/{lab}"
    rules: list[dict[str, Any]] = [
        _rule("orchestrator", _ALL, ["ingress", "egress"], [f"{p}/**"]),
        _rule("scheduler-in", ["declare_queryable", "reply", "liveliness_token"], ["ingress"],
              [f"{p}/agent/scheduler/**"]),
        _rule("scheduler-out", ["query"], ["egress"], [f"{p}/agent/scheduler/**"]),
        *_claiming("scheduler", [keys.claim(lab, "agent"), f"{p}/agent/scheduler/alive"]),
        _rule("clock-ask", ["declare_subscriber", "query"], ["ingress"], [keys.clock(lab)]),
        _rule("clock-told", ["put", "reply"], ["egress"], [keys.clock(lab)]),
        # whether the lab's campaign is on the bus: a device stops a step it can no longer supervise, and a joining
        # process asks for the lab's time again when a campaign comes (another run starts its time again)
        _rule("campaign-watch", ["declare_liveliness_subscriber", "liveliness_query"], ["ingress"],
              [keys.orchestrator(lab)]),
        _rule("campaign-seen", ["liveliness_token", "reply"], ["egress"], [keys.orchestrator(lab)]),
        _rule("watcher-in", ["declare_subscriber", "declare_liveliness_subscriber", "liveliness_query"], ["ingress"],
              [f"{p}/**"]),
        _rule("watcher-history", ["query"], ["ingress"], [keys.campaign(lab, "*", "history")]),
        _rule("watcher-out", ["put", "reply", "liveliness_token"], ["egress"], [f"{p}/**"]),
        _rule("operator-ask", ["query"], ["ingress"], [keys.control(lab, "**")]),
        _rule("operator-answered", ["reply"], ["egress"], [keys.control(lab, "**")]),
    ]
    subjects = [{"id": role, "cert_common_names": [Identity(role, lab).common_name]}
                for role in ("orchestrator", "scheduler", "watcher", "operator")]
    policies = [{"rules": ["orchestrator"], "subjects": ["orchestrator"]},
                {"rules": ["scheduler-in", "scheduler-out", "scheduler-claim", "scheduler-claim-seen", *_JOINER],
                 "subjects": ["scheduler"]},
                {"rules": ["watcher-in", "watcher-history", "watcher-out"], "subjects": ["watcher"]},
                {"rules": ["operator-ask", "operator-answered"], "subjects": ["operator"]}]
    for i, dev in enumerate(devices):
        sid = f"device{i}"
        own = [
            _rule(f"{sid}-say", ["put"], ["ingress"], [keys.evt(lab, dev), keys.telemetry(lab, dev)]),
            _rule(f"{sid}-listen", ["declare_subscriber"], ["ingress"], [keys.cmd(lab, dev)]),
            _rule(f"{sid}-hear", ["put"], ["egress"], [keys.cmd(lab, dev)]),
            _rule(f"{sid}-present", ["liveliness_token"], ["ingress"], [keys.alive(lab, dev)]),
            _rule(f"{sid}-health", ["declare_queryable", "reply"], ["ingress"], [keys.health(lab, dev)]),
            _rule(f"{sid}-asked", ["query"], ["egress"], [keys.health(lab, dev)]),
            *_claiming(sid, [keys.claim(lab, f"dev/{dev}"), keys.alive(lab, dev)]),
        ]
        rules += own
        subjects.append({"id": sid, "cert_common_names": [Identity("device", lab, dev).common_name]})
        policies.append({"rules": [r["id"] for r in own] + list(_JOINER), "subjects": [sid]})
    return {"enabled": True, "default_permission": "deny", "rules": rules, "subjects": subjects,
            "policies": policies}


#: what every process that joins the lab may do: follow its clock, and see whether its campaign is on the bus
_JOINER = ("clock-ask", "clock-told", "campaign-watch", "campaign-seen")


def _claiming(rid: str, key_exprs: list[str]) -> list[dict[str, Any]]:
    """Claiming a part of the lab before serving it, and seeing whether another process holds or claims it too
    (twin/runtime/lab_claim.py)."""
    return [_rule(f"{rid}-claim", ["liveliness_token", "declare_liveliness_subscriber", "liveliness_query"],
                  ["ingress"], key_exprs),
            _rule(f"{rid}-claim-seen", ["liveliness_token", "reply"], ["egress"], key_exprs)]


def _rule(rid: str, messages: list[str], flows: list[str], key_exprs: list[str]) -> dict[str, Any]:
    return {"id": rid, "messages": messages, "flows": flows, "permission": "allow", "key_exprs": key_exprs}


def is_loopback(endpoint: str) -> bool:
    """``tcp/127.0.0.1:7447`` → True; ``tcp/0.0.0.0:7447`` or ``tls/lab.example:7447`` → False."""
    _, _, address = endpoint.partition("/")
    host = address.split("#")[0].rsplit(":", 1)[0].strip("[]")
    if host == "localhost":
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return False


def check_listen(endpoints: list[str], *, secure: bool, insecure: bool, what: str) -> list[str]:
    """Refuse to listen beyond loopback without security (or an explicit ``--insecure``); the warnings to log."""
    exposed = [e for e in endpoints if not is_loopback(e)]
    if not exposed:
        return []
    if secure:
        plain = [e for e in exposed if not e.startswith(("tls/", "quic/"))]
        if plain:
            raise BusError(f"{what}: {plain} would accept connections without TLS, outside the lab's access "
                           "control: listen on tls/HOST:PORT")
        return []
    if not insecure:
        raise BusError(f"{what}: refusing to listen on {exposed} without security: anyone who reaches it can read "
                       "every message and forge commands and results. Make the lab's certificates (`twin security "
                       "init`) and pass --security DIR, listen on 127.0.0.1, or pass --insecure if that network is "
                       "yours alone")
    return [f"{what}: listening on {exposed} WITHOUT security (--insecure): anyone who reaches it can read every "
            "message, and, while they can see the commands, forge results"]
