#!/usr/bin/env python3
"""A stand-alone instrument that speaks labtwin's MQTT protocol (docs/mqtt.md): a plate reader measuring
quantum-dot samples. It knows nothing of labtwin.

    python examples/mqtt_instrument.py --broker 127.0.0.1:1883 --topic lab/reader-1 --seconds 1

It listens on ``<topic>/command``: a run command is measured for ``--seconds`` (wall time), reporting
``progress`` half way, and answered on ``<topic>/result`` with ``{"id", "outputs", "sample"}`` (the sample's
emission peak and line width with a little noise); a second command while one runs is refused as busy; a cancel
stops it (after ``--cancel-seconds``, a slow instrument) and is acknowledged ``{"id", "cancelled": true}``; a
ping re-announces ``online``. ``<topic>/status`` is ``online`` (retained) while it runs, ``offline`` when it
exits (explicitly) or dies (its MQTT last will); ``<topic>/health`` (retained) says how it is. A broker lost
is connected again every second, and ``online`` said again.
"""

from __future__ import annotations

import argparse
import asyncio
import json
import os
import random
import signal
import socket
import sys

import aiomqtt


async def measure(pub, cmd: dict, seconds: float, rng: random.Random) -> None:
    await asyncio.sleep(seconds / 2)
    await pub("progress", {"id": cmd["id"], "fraction": 0.5, "note": "half way"})
    await asyncio.sleep(seconds / 2)
    sample = cmd.get("sample") or {}
    if "peak_nm" not in sample:
        await pub("result", {"id": cmd["id"], "error": f"nothing to measure in sample {sample!r:.80}"})
        return
    outputs = {"peak_nm": round(sample["peak_nm"] + rng.gauss(0, 0.5), 3),
               "fwhm_nm": round(sample.get("fwhm_nm", 30.0) * (1 + rng.gauss(0, 0.01)), 3)}
    await pub("result", {"id": cmd["id"], "outputs": outputs, "sample": sample})


async def main(args: argparse.Namespace) -> None:
    stop = asyncio.Event()
    for sig in (signal.SIGINT, signal.SIGTERM):
        asyncio.get_running_loop().add_signal_handler(sig, stop.set)
    rng, said = random.Random(args.seed), []

    def ready(topic: str) -> None:
        if not said:  # once, when it first is
            said.append(print(f"ready {topic}", flush=True))

    while not stop.is_set():  # a broker lost (restarted, unreachable): connect again every second
        try:
            await session(args, rng, stop, ready)
        except aiomqtt.MqttError as exc:
            print(f"no broker ({exc}); connecting again in 1 s", file=sys.stderr, flush=True)
            await asyncio.sleep(1)


async def session(args: argparse.Namespace, rng: random.Random, stop: asyncio.Event, ready) -> None:
    """One session with the broker, until ``stop`` (then ``offline``) or until the broker goes (MqttError)."""
    host, _, port = args.broker.rpartition(":")
    t, running = args.topic, {}
    will = aiomqtt.Will(f"{t}/status", "offline", qos=1, retain=True)
    tls = aiomqtt.TLSParameters(ca_certs=args.ca) if args.ca else None
    async with aiomqtt.Client(host, int(port), identifier=f"instrument-{t}", will=will, keepalive=args.keepalive,
                              username=args.username, tls_params=tls,
                              password=os.environ.get(args.password_env) if args.password_env else None,
                              socket_options=((socket.IPPROTO_TCP, socket.TCP_NODELAY, 1),)) as client:

        async def pub(topic: str, body, retain: bool = False) -> None:
            await client.publish(f"{t}/{topic}", body if isinstance(body, str) else json.dumps(body), qos=1,
                                 retain=retain)

        async def cancel(cmd: dict, task: asyncio.Task) -> None:
            await asyncio.sleep(args.cancel_seconds)
            task.cancel()
            running.pop(cmd["id"], None)
            await pub("result", {"id": cmd["id"], "cancelled": True})

        async def serve() -> None:
            async for message in client.messages:
                cmd = json.loads(message.payload)
                if cmd.get("ping"):
                    await pub("status", "online", retain=True)
                elif cmd.get("cancel"):
                    if cmd["id"] in running:
                        asyncio.ensure_future(cancel(cmd, running[cmd["id"]]))
                elif any(not task.done() for task in running.values()):
                    await pub("result", {"id": cmd["id"], "refused": "busy", "infeasible": False})
                else:
                    running.clear()
                    running[cmd["id"]] = asyncio.ensure_future(measure(pub, cmd, args.seconds, rng))

        await client.subscribe(f"{t}/command", qos=1)
        await pub("health", {"ok": True, "lamp_hours": 1234}, retain=True)
        await pub("status", "online", retain=True)
        ready(t)
        server, stopping = asyncio.ensure_future(serve()), asyncio.ensure_future(stop.wait())
        await asyncio.wait({server, stopping}, return_when=asyncio.FIRST_COMPLETED)
        for task in (server, stopping, *running.values()):
            task.cancel()
        if not stop.is_set():  # the session ended by itself: the broker went
            if server.done() and not server.cancelled() and server.exception() is not None:
                raise server.exception()
            raise aiomqtt.MqttError("the broker ended the session")
        await pub("status", "offline", retain=True)  # a clean disconnect does not fire the last will


if __name__ == "__main__":
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--broker", default="127.0.0.1:1883")
    ap.add_argument("--topic", required=True)
    ap.add_argument("--seconds", type=float, default=1.0, help="wall seconds per measurement")
    ap.add_argument("--cancel-seconds", type=float, default=0.0, help="wall seconds it takes to stop when cancelled")
    ap.add_argument("--keepalive", type=int, default=2, help="seconds; a frozen instrument is declared dead after 1.5x")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--username", help="the broker's user for this instrument")
    ap.add_argument("--password-env", help="the environment variable that holds its password")
    ap.add_argument("--ca", help="the CA certificate (PEM) of a broker that speaks TLS")
    asyncio.run(main(ap.parse_args()))
