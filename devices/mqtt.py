"""An instrument that speaks JSON over MQTT, as an ordinary device of the lab.

The protocol — topics, payloads, presence, cancellation, what is done with a
message that breaks it — is docs/mqtt.md; ``devices/mqtt_protocol.py`` checks
the payloads. In short, under ``options.topic`` (say ``lab/hplc-1``): the lab
sends ``command`` (run, cancel, ping); the instrument answers on ``result``,
says ``online``/``offline`` on ``status`` (retained, with its last will),
and may publish ``progress``, ``telemetry`` and ``health``.

The device's presence on the lab bus follows ``status``, and a retained
``online`` is trusted only once the instrument has answered a ping (a clean
disconnect does not fire the last will). Deadlines and retries are the
orchestrator's; commands carry them in wall seconds with the lab's clock speed.
A broker lost takes the instrument off the bus; the adapter connects again
every second until the broker is back.
Options: ``broker`` (``host:port``, default ``127.0.0.1:1883``), ``topic``
(``{name}`` in it is the device instance's name), ``steps`` (what the instrument
runs), ``qos`` (default 1), ``outputs`` (what its results hold, for ``twin
validate``), ``connect_timeout_s`` (wall seconds to wait for the broker to answer a connect, subscribe or
publish, default 10),
``cancel_wait_s`` (wall seconds to wait for the instrument to
acknowledge a cancel, default 10), ``username`` with ``password`` or
``password_env`` (the name of an environment variable that holds it), and
``tls: {ca, cert, key}`` (PEM files). docs/security.md has a mosquitto
configuration with an ACL.
"""

from __future__ import annotations

import asyncio
import collections
import contextlib
import itertools
import logging
import os
import secrets
import socket
import ssl
from collections.abc import Callable
from typing import Any

import aiomqtt
from aiomqtt.exceptions import MqttConnectError

from devices import mqtt_protocol as proto
from twin import DriverError, DriverSetup, Refused, StepContext, StepResult, sleep_wall, wall_on_loop

log = logging.getLogger(__name__)
NODELAY = ((socket.IPPROTO_TCP, socket.TCP_NODELAY, 1),)  # without it p99 round trips were ~40 ms
PING_EVERY_WALL_S = 2.0
OFFLINE_PINGS = 3  # after an "offline": enough to hear a live instrument whose old session's will came late
RECONNECT_EVERY_WALL_S = 1.0
SILENT_SAY_AFTER_WALL_S = 5.0  # an instrument not present by then is said once, with where the adapter listens

class MqttInstrument:
    labtwin_api = 1
    realtime = True  # a real instrument keeps wall time: the lab's clock must be scaled or wall
    option_names = frozenset({"broker", "topic", "steps", "outputs", "qos", "cancel_wait_s", "connect_timeout_s",
                              "tls", "username", "password", "password_env"})

    def __init__(self, setup: DriverSetup) -> None:
        o = setup.options
        if not o.get("topic"):
            raise DriverError(f"{setup.name}: options.topic is required (the instrument's MQTT topic prefix)")
        host, _, port = str(o.get("broker", "127.0.0.1:1883")).rpartition(":")
        self.host, self.port = host or "127.0.0.1", int(port)
        # "{name}" in the topic is the device instance: one instrument per instance
        self.topic_option = str(o["topic"])
        self.topic = self.topic_option.replace("{name}", setup.name).rstrip("/")
        self.qos, self.name = int(o.get("qos", 1)), setup.name
        self.claims = (f"the MQTT topic {self.topic} at {self.host}:{self.port} (options.topic; {{name}} in it gives "
                       "each instance its own)")
        self.cancel_wait_s = float(o.get("cancel_wait_s", 10.0))
        self.connect_timeout_s = float(o.get("connect_timeout_s", 10.0))
        self.capabilities = frozenset(o.get("steps") or ())
        self.username, self.password = _credentials(setup.name, o)
        self.tls = _tls(setup.name, o.get("tls"))
        self.dropped = 0
        if o.get("outputs") is not None:  # what the instrument's results hold, when the scenario says
            self.outputs = frozenset(str(x) for x in o["outputs"])
        self._ids = itertools.count(1)
        self._job: str | None = None  # the command the instrument is running
        self._answer: asyncio.Future | None = None
        self._ctx: StepContext | None = None
        self._issued: collections.deque[str] = collections.deque(maxlen=256)  # late answers are not strangers
        self._client: aiomqtt.Client | None = None
        self._tasks: list[asyncio.Task] = []
        self._pinger: asyncio.Task | None = None  # what pings the instrument to learn whether it is there
        self._present: bool | None = None  # None: a retained "online" not yet confirmed by a ping
        self._heard: str | None = None  # the last status heard: "online", "retained online" or "offline"
        self._presence: Callable[[bool], None] = lambda present: None
        self._instrument_health: Any = None
        self._telemetry: dict[str, float] = {}

    # -- life cycle (called by the device actor) -------------------------------------
    async def connect(self, presence: Callable[[bool], None]) -> None:
        self._presence = presence
        await self._open()
        self._tasks = [asyncio.ensure_future(self._receive()), asyncio.ensure_future(self._say_if_absent())]
        # nothing retained there: an instrument that said online before this session began, without retain (or to a
        # broker that has since forgotten it), is found by its answer to a ping
        self._ping_while(lambda: self._heard is None)

    async def _say_if_absent(self) -> None:
        """Once, a while after connecting: where the adapter waits for an instrument that is not there, and what it
        last heard, so that a topic that is not the instrument's is seen in the log rather than guessed at."""
        await sleep_wall(SILENT_SAY_AFTER_WALL_S)
        if self._present is True:
            return
        heard = {None: "nothing has been said there, and no ping has been answered",
                 "offline": "the last word there was offline",
                 "retained online": "the only word there is an old retained online, and no ping has been answered "
                 "since (the instrument that left it has gone)"}.get(self._heard, f"the last word was {self._heard}")
        named = f"; {{name}} is this device's name, {self.name!r}" if "{name}" in self.topic_option else ""
        log.warning("%s: no instrument present on %s/status at the MQTT broker %s:%d after %g s of wall time: %s. The "
                    "device stays off the lab's bus until its instrument says online there: is it running, on this "
                    "broker and topic (options.topic %r%s)?", self.name, self.topic, self.host, self.port,
                    SILENT_SAY_AFTER_WALL_S, heard, self.topic_option, named)

    async def _open(self) -> None:
        """A session with the broker, subscribed to the instrument's topics; a DriverError says why not."""
        # aiomqtt times a connect and a subscription on the running loop, whose time is lab time: at 100× the
        # 10 s the option means were 0.1 s of wall time, and a busy broker missed them
        client = aiomqtt.Client(self.host, self.port, identifier=f"labtwin-{self.name}-{id(self):x}",
                                socket_options=NODELAY, username=self.username, password=self.password,
                                tls_params=self.tls, timeout=wall_on_loop(self.connect_timeout_s))
        where = f"the MQTT broker at {self.host}:{self.port}"
        try:
            await client.__aenter__()
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
        try:
            for topic, _retained in proto.TOPICS.items():
                if topic != "command":
                    await client.subscribe(f"{self.topic}/{topic}", qos=self.qos)
        except aiomqtt.MqttError as exc:
            with contextlib.suppress(Exception):
                await client.__aexit__(None, None, None)
            raise DriverError(f"{self.name}: {where} did not take the subscriptions ({exc})") from exc
        self._client = client

    async def disconnect(self) -> None:
        for task in self._tasks:
            task.cancel()
            with contextlib.suppress(asyncio.CancelledError, Exception):
                await task
        if self._client is not None:
            with contextlib.suppress(Exception):
                await self._client.__aexit__(None, None, None)
        self._client = None

    async def _receive(self) -> None:
        """Hand each message to its topic's handler; when the broker goes, the instrument is gone with it until
        a session is open again (tried every ``RECONNECT_EVERY_WALL_S``) and the instrument says it is there."""
        while True:
            client = self._client
            assert client is not None
            try:
                async for message in client.messages:
                    payload = message.payload if isinstance(message.payload, bytes) else str(message.payload).encode()
                    topic = str(message.topic)[len(self.topic) + 1:]
                    handle = getattr(self, f"_on_{topic}", None)
                    if handle is not None:
                        handle(payload, bool(message.retain))
                return
            except aiomqtt.MqttError as exc:
                log.warning("%s: lost the MQTT broker (%s); connecting again every %g s", self.name, exc,
                            RECONNECT_EVERY_WALL_S)
            self._client = None
            self._set_present(False)
            if self._answer is not None and not self._answer.done():  # its answer went with the broker
                self._answer.set_exception(DriverError(f"{self.name}: lost the MQTT broker during the step"))
            with contextlib.suppress(Exception):
                await client.__aexit__(None, None, None)
            await self._reopen()

    async def _reopen(self) -> None:
        tries = 0
        while self._client is None:
            await sleep_wall(RECONNECT_EVERY_WALL_S)
            tries += 1
            try:
                await self._open()
            except DriverError as exc:
                if tries in (1, 10) or tries % 100 == 0:
                    log.warning("%s: still no MQTT broker after %d tries (%s)", self.name, tries, exc)
        log.info("%s: connected to the MQTT broker again; waiting for the instrument to say it is online", self.name)

    # -- what the instrument says ------------------------------------------------------
    def _on_status(self, payload: bytes, retained: bool) -> None:
        text = payload.decode(errors="replace").strip().strip('"')
        if text in ("online", "offline"):
            self._heard = "retained online" if text == "online" and retained else text
        if text == "offline":
            self._set_present(False)
            if self._answer is not None and not self._answer.done():  # the command died with it: end the step now
                self._answer.set_exception(DriverError(f"{self.name}: the instrument went offline during the step"))
            # a late last will: an instrument back on a new session (another client id) before the broker saw its
            # old one end says "online" first, and its old will "offline" after; a live instrument answers a ping
            self._ping_while(lambda: self._present is False, OFFLINE_PINGS)
        elif text != "online":
            self._invalid("status", f"{text[:40]!r}, not online or offline")
        elif not retained:
            self._set_present(True)
        elif not self._present:  # a retained "online" may be a dead instrument's that exited without a will
            self._present = None
            self._ping_while(lambda: self._present is None)

    def _set_present(self, present: bool) -> None:
        if self._present is not present:
            self._present = present
            self._presence(present)

    def _ping_while(self, still: Callable[[], bool], times: int | None = None) -> None:
        """Ping the instrument every ``PING_EVERY_WALL_S`` while ``still()``, at most ``times`` times (one pinger at a
        time: a new one replaces the last)."""
        async def pings() -> None:
            n = 0
            while still() and self._client is not None and (times is None or n < times):
                with contextlib.suppress(aiomqtt.MqttError):
                    await self._client.publish(f"{self.topic}/command", proto.ping(self._new_id()), qos=self.qos)
                n += 1
                await sleep_wall(PING_EVERY_WALL_S)

        if self._pinger is not None:
            self._pinger.cancel()
        self._pinger = asyncio.ensure_future(pings())
        self._tasks = [t for t in self._tasks if not t.done()] + [self._pinger]

    def _on_result(self, payload: bytes, retained: bool) -> None:
        try:
            data = proto.parse(payload)
            job = proto.job_of(data)
            kind = proto.result_kind(data)
        except proto.InvalidPayload as exc:
            self._fail_running(f"an invalid result ({exc})")
            return
        if job != self._job:
            if job in self._issued:
                self._invalid("result", f"a late or repeated answer to {job[:60]!r}", quiet=True)
            else:
                self._fail_running(f"a result for {job[:60]!r}, a command id this adapter never issued")
            return
        if self._answer is not None and not self._answer.done():
            self._answer.set_result((kind, data))

    def _on_progress(self, payload: bytes, retained: bool) -> None:
        try:
            data = proto.parse(payload)
            fraction, note = proto.progress(data)
        except proto.InvalidPayload as exc:
            self._invalid("progress", str(exc))
            return
        if self._ctx is not None and data.get("id") == self._job:
            self._ctx.progress(fraction, note)

    def _on_telemetry(self, payload: bytes, retained: bool) -> None:
        try:
            self._telemetry = proto.readings(proto.parse(payload))
        except proto.InvalidPayload as exc:
            self._invalid("telemetry", str(exc))
            return
        if self._ctx is not None:
            self._ctx.telemetry(self._telemetry)

    def _on_health(self, payload: bytes, retained: bool) -> None:
        try:
            self._instrument_health = proto.parse(payload)
        except proto.InvalidPayload as exc:
            self._invalid("health", str(exc))

    def _fail_running(self, what: str) -> None:
        """A broken result fails the step it must be about (one at a time) at once, not at its deadline."""
        self._invalid("result", what)
        if self._answer is not None and not self._answer.done():
            self._answer.set_exception(DriverError(f"{self.name}: the instrument sent {what}"[:500]))

    def _invalid(self, topic: str, what: str, quiet: bool = False) -> None:
        self.dropped += 1
        if not quiet and (self.dropped <= 10 or self.dropped % 1000 == 0):
            log.warning("%s: dropped on %s/%s: %s (%d so far)", self.name, self.topic, topic, what, self.dropped)

    def _new_id(self) -> str:
        job = f"{self.name}-{next(self._ids)}-{secrets.token_hex(8)}"  # unguessable: only the instrument knows it
        self._issued.append(job)
        return job

    # -- the driver contract -------------------------------------------------------------
    async def run(self, step: str, params: dict[str, Any], sample: dict | None, ctx: StepContext) -> StepResult:
        if self._client is None:
            raise DriverError(f"{self.name}: not connected to the MQTT broker")
        speed = ctx.clock.speed if ctx.clock.speed > 0 else 1.0
        job = self._job = self._new_id()
        self._answer, self._ctx = asyncio.get_running_loop().create_future(), ctx
        text = proto.command(job, step, params, sample, expected_s=ctx.expected_s / speed,
                             deadline_s=None if ctx.deadline_s is None else ctx.deadline_s / speed, speed=speed,
                             t_lab=ctx.clock.now())
        try:
            await self._client.publish(f"{self.topic}/command", text, qos=self.qos)
            kind, reply = await asyncio.shield(self._answer)  # a cancel must leave it to the instrument's answer
        except asyncio.CancelledError:
            await self._cancel(job)
            raise
        finally:
            self._job = self._answer = self._ctx = None
        if kind == "done":
            return StepResult(reply["outputs"], reply["sample"])
        if kind == "refused":
            raise Refused(reply["refused"], bool(reply.get("infeasible", False)))
        if kind == "cancelled":
            raise DriverError(f"{self.name}: the instrument cancelled {step} by itself")
        raise DriverError(f"{self.name} reported: {reply['error']}")

    async def _cancel(self, job: str) -> None:
        """Tell the instrument, and wait (``cancel_wait_s`` of wall time) for it to say it stopped: until then
        the device is not free for the next command."""
        with contextlib.suppress(Exception):
            await self._client.publish(f"{self.topic}/command", proto.cancel(job), qos=self.qos)
        answer = self._answer
        if answer is None:
            return
        waited = asyncio.ensure_future(sleep_wall(self.cancel_wait_s))
        await asyncio.wait({answer, waited}, return_when=asyncio.FIRST_COMPLETED)
        waited.cancel()
        if not answer.done():
            log.warning("%s: the instrument did not acknowledge the cancel of %s in %g s of wall time", self.name,
                        job, self.cancel_wait_s)
        elif answer.exception() is None and answer.result()[0] != "cancelled":
            log.info("%s: the instrument finished %s as it was cancelled; its answer is not counted", self.name, job)

    async def safe_state(self) -> None:
        """The instrument keeps its own safe state; a cancelled step was already told to stop."""

    async def health(self) -> dict[str, Any]:
        return {"ok": self._client is not None and self._present is True, "broker": f"{self.host}:{self.port}",
                "topic": self.topic, "present": self._present, "running": self._job, "dropped": self.dropped,
                "tls": self.tls is not None, "user": self.username, "instrument": self._instrument_health,
                "telemetry": self._telemetry}


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
