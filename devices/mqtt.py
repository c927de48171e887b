"""An instrument that speaks JSON over MQTT, as an ordinary device of the lab.

Topics under ``options.topic`` (say ``lab/hplc-1``):

- ``<topic>/command`` ← ``{"id", "step", "params", "sample"}`` to run a step, ``{"id", "cancel": true}`` to stop it;
- ``<topic>/result``  → ``{"id", "outputs": {...}, "sample": {...}}``, or ``{"id", "error": "why"}``;
- ``<topic>/status``  → ``"online"`` (retained) when the instrument is up; its MQTT last will says ``"offline"``.

The device's presence on the lab bus follows ``status``: the instrument's last
will (it died, or lost the broker) takes the device off the bus, so the
orchestrator sees the loss as it sees any other and moves the work. Deadlines
and retries are the orchestrator's, as for every driver. Options: ``broker``
(``host:port``, default ``127.0.0.1:1883``), ``topic`` (``{name}`` in it is
the device instance's name), ``steps`` (what the instrument runs), ``qos``
(default 1), ``outputs`` (what its results hold, for ``twin validate``),
``username`` with ``password`` or ``password_env`` (the name of an environment
variable that holds it: a password is best kept out of scenario files), and
``tls: {ca, cert, key}`` (PEM files; ``cert``/``key`` for a client
certificate). docs/security.md has a mosquitto configuration with an ACL.

A result counts only for a command id this adapter issued (random, so it
cannot be guessed) and only once; anything else is dropped, logged and
counted in the device's health report.
"""

from __future__ import annotations

import asyncio
import contextlib
import itertools
import json
import logging
import os
import secrets
import socket
import ssl
from collections.abc import Callable
from typing import Any

import aiomqtt
from aiomqtt.exceptions import MqttConnectError

from twin import DriverSetup, StepContext, StepResult
from twin import DriverError

log = logging.getLogger(__name__)
NODELAY = ((socket.IPPROTO_TCP, socket.TCP_NODELAY, 1),)  # without it p99 round trips were ~40 ms


class MqttInstrument:
    labtwin_api = 1
    realtime = True  # a real instrument keeps wall time: the lab's clock must be scaled or wall

    def __init__(self, setup: DriverSetup) -> None:
        o = setup.options
        if not o.get("topic"):
            raise DriverError(f"{setup.name}: options.topic is required (the instrument's MQTT topic prefix)")
        host, _, port = str(o.get("broker", "127.0.0.1:1883")).rpartition(":")
        self.host, self.port = host or "127.0.0.1", int(port)
        # "{name}" in the topic is the device instance: one instrument per instance
        self.topic = str(o["topic"]).replace("{name}", setup.name).rstrip("/")
        self.qos, self.name = int(o.get("qos", 1)), setup.name
        self.capabilities = frozenset(o.get("steps") or ())
        self.username, self.password = _credentials(setup.name, o)
        self.tls = _tls(setup.name, o.get("tls"))
        self.dropped = 0
        if o.get("outputs") is not None:  # what the instrument's results hold, when the scenario says
            self.outputs = frozenset(str(x) for x in o["outputs"])
        self._ids = itertools.count(1)
        self._waiting: dict[str, asyncio.Future] = {}
        self._client: aiomqtt.Client | None = None
        self._pump: asyncio.Task | None = None
        self._presence: Callable[[bool], None] = lambda present: None

    # -- life cycle (called by the device actor) -------------------------------------
    async def connect(self, presence: Callable[[bool], None]) -> None:
        self._presence = presence
        self._client = aiomqtt.Client(self.host, self.port, identifier=f"labtwin-{self.name}-{id(self):x}",
                                      socket_options=NODELAY, username=self.username, password=self.password,
                                      tls_params=self.tls)
        where = f"the MQTT broker at {self.host}:{self.port}"
        try:
            await self._client.__aenter__()
        except MqttConnectError as exc:  # it answered, and said no
            who = f"user {self.username!r}" if self.username else "an anonymous client"
            raise DriverError(f"{self.name}: {where} refused {who} ({getattr(exc, 'rc', exc)}): check "
                              "options.username and the password against the broker's password file") from exc
        except aiomqtt.MqttError as exc:
            cause = f"{exc} {exc.__cause__ or ''}"
            if self.tls is not None and ("SSL" in cause or "certificate" in cause.lower()):
                raise DriverError(f"{self.name}: the TLS handshake with {where} failed ({exc}): check options.tls.ca "
                                  "(the CA that signed the broker's certificate) and that this port speaks TLS") from exc
            raise DriverError(f"{self.name}: cannot reach {where} ({exc}): is it running, and listening on that "
                              f"port{' with TLS' if self.tls else ''}?") from exc
        await self._client.subscribe(f"{self.topic}/result", qos=self.qos)
        await self._client.subscribe(f"{self.topic}/status", qos=self.qos)
        self._pump = asyncio.ensure_future(self._receive())

    async def disconnect(self) -> None:
        if self._pump is not None:
            self._pump.cancel()
            with contextlib.suppress(asyncio.CancelledError, Exception):
                await self._pump
        if self._client is not None:
            with contextlib.suppress(Exception):
                await self._client.__aexit__(None, None, None)
        self._client = None

    async def _receive(self) -> None:
        try:
            async for message in self._client.messages:
                text = message.payload.decode(errors="replace") if isinstance(message.payload, bytes) else str(message.payload)
                if message.topic.matches(f"{self.topic}/status"):
                    self._presence(text.strip('"') == "online")
                else:
                    self._answer(text)
        except aiomqtt.MqttError as exc:
            log.warning("%s: lost the MQTT broker (%s)", self.name, exc)
            self._presence(False)

    def _answer(self, text: str) -> None:
        try:
            reply = json.loads(text)
            waiter = self._waiting.pop(str(reply["id"]), None)
        except (ValueError, KeyError, TypeError, AttributeError):
            self.dropped += 1
            log.warning("%s: dropped an unreadable result %.200r", self.name, text)
            return
        if waiter is None or waiter.done():
            self.dropped += 1
            log.warning("%s: dropped a result for %.60r, a command id this adapter did not issue or already "
                        "counted", self.name, str(reply.get("id")))
            return
        waiter.set_result(reply)

    # -- the driver contract -------------------------------------------------------------
    async def run(self, step: str, params: dict[str, Any], sample: dict | None, ctx: StepContext) -> StepResult:
        if self._client is None:
            raise DriverError(f"{self.name}: not connected to the MQTT broker")
        job = f"{self.name}-{next(self._ids)}-{secrets.token_hex(8)}"  # unguessable: only the instrument knows it
        waiter = self._waiting[job] = asyncio.get_running_loop().create_future()
        command = {"id": job, "step": step, "params": params, "sample": sample}
        try:
            await self._client.publish(f"{self.topic}/command", json.dumps(command), qos=self.qos)
            reply = await waiter
        except asyncio.CancelledError:
            self._waiting.pop(job, None)
            with contextlib.suppress(Exception):
                await self._client.publish(f"{self.topic}/command", json.dumps({"id": job, "cancel": True}), qos=self.qos)
            raise
        if "error" in reply:
            raise DriverError(f"{self.name} reported: {reply['error']}")
        outputs = reply.get("outputs")
        if not isinstance(outputs, dict):
            raise DriverError(f"{self.name} sent a result without an 'outputs' object: {reply!r:.200}")
        return StepResult(outputs, reply.get("sample", sample))

    async def safe_state(self) -> None:
        """The instrument keeps its own safe state; a cancelled step was already told to stop."""

    async def health(self) -> dict[str, Any]:
        return {"ok": self._client is not None, "broker": f"{self.host}:{self.port}", "topic": self.topic,
                "waiting": len(self._waiting), "dropped": self.dropped, "tls": self.tls is not None,
                "user": self.username}


def _credentials(name: str, o: dict[str, Any]) -> tuple[str | None, str | None]:
    user, password, env = o.get("username"), o.get("password"), o.get("password_env")
    if env:
        password = os.environ.get(str(env))
        if password is None:
            raise DriverError(f"{name}: options.password_env names ${env}, which is not set in this environment")
    if password is not None and not user:
        raise DriverError(f"{name}: a password without options.username")
    return (str(user) if user else None), (str(password) if password is not None else None)


def _tls(name: str, tls: Any) -> aiomqtt.TLSParameters | None:
    if tls is None:
        return None
    if not isinstance(tls, dict) or not tls.get("ca"):
        raise DriverError(f"{name}: options.tls must be {{ca: PATH[, cert: PATH, key: PATH]}} (PEM files)")
    for field in ("ca", "cert", "key"):
        if tls.get(field) and not os.path.isfile(tls[field]):
            raise DriverError(f"{name}: options.tls.{field}: {tls[field]!r} is not a file")
    if bool(tls.get("cert")) != bool(tls.get("key")):
        raise DriverError(f"{name}: options.tls: give cert and key together (a client certificate)")
    return aiomqtt.TLSParameters(ca_certs=tls["ca"], certfile=tls.get("cert"), keyfile=tls.get("key"),
                                 cert_reqs=ssl.CERT_REQUIRED, tls_version=ssl.PROTOCOL_TLS_CLIENT)
