#!/usr/bin/env python3
"""A stand-alone instrument that speaks JSON over MQTT: a plate reader measuring quantum-dot samples.

It knows nothing of labtwin. It listens on ``<topic>/command``, answers on
``<topic>/result`` and says ``online`` on ``<topic>/status`` (retained); its
MQTT last will says ``offline``, so the broker tells the lab when it dies.

    python examples/mqtt_instrument.py --broker 127.0.0.1:1883 --topic lab/reader-1 --seconds 1

A command ``{"id", "step", "params", "sample"}`` is measured for ``--seconds``
(wall time) and answered ``{"id", "outputs", "sample"}``: the sample's emission
peak and line width with a little noise. ``{"id", "cancel": true}`` stops it.
"""

from __future__ import annotations

import argparse
import asyncio
import json
import os
import random
import signal
import socket

import aiomqtt


async def measure(client: aiomqtt.Client, topic: str, cmd: dict, seconds: float, rng: random.Random) -> None:
    await asyncio.sleep(seconds)
    sample = cmd.get("sample") or {}
    if "peak_nm" not in sample:
        reply = {"id": cmd["id"], "error": f"nothing to measure in sample {sample!r:.80}"}
    else:
        outputs = {"peak_nm": round(sample["peak_nm"] + rng.gauss(0, 0.5), 3),
                   "fwhm_nm": round(sample.get("fwhm_nm", 30.0) * (1 + rng.gauss(0, 0.01)), 3)}
        reply = {"id": cmd["id"], "outputs": outputs, "sample": sample}
    await client.publish(f"{topic}/result", json.dumps(reply), qos=1)


async def main(args: argparse.Namespace) -> None:
    host, _, port = args.broker.rpartition(":")
    will = aiomqtt.Will(f"{args.topic}/status", "offline", qos=1, retain=True)
    rng, running = random.Random(args.seed), {}
    stop = asyncio.Event()
    for sig in (signal.SIGINT, signal.SIGTERM):
        asyncio.get_running_loop().add_signal_handler(sig, stop.set)
    tls = aiomqtt.TLSParameters(ca_certs=args.ca) if args.ca else None
    async with aiomqtt.Client(host, int(port), identifier=f"instrument-{args.topic}", will=will,
                              keepalive=args.keepalive, username=args.username,
                              password=os.environ.get(args.password_env) if args.password_env else None,
                              tls_params=tls,
                              socket_options=((socket.IPPROTO_TCP, socket.TCP_NODELAY, 1),)) as client:
        await client.subscribe(f"{args.topic}/command", qos=1)
        await client.publish(f"{args.topic}/status", "online", qos=1, retain=True)
        print(f"ready {args.topic}", flush=True)

        async def serve() -> None:
            async for message in client.messages:
                cmd = json.loads(message.payload)
                if cmd.get("cancel"):
                    task = running.pop(cmd["id"], None)
                    if task:
                        task.cancel()
                    continue
                running[cmd["id"]] = asyncio.ensure_future(measure(client, args.topic, cmd, args.seconds, rng))

        server = asyncio.ensure_future(serve())
        await stop.wait()
        server.cancel()
        await client.publish(f"{args.topic}/status", "offline", qos=1, retain=True)


if __name__ == "__main__":
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--broker", default="127.0.0.1:1883")
    ap.add_argument("--topic", required=True)
    ap.add_argument("--seconds", type=float, default=1.0, help="wall seconds per measurement")
    ap.add_argument("--keepalive", type=int, default=2, help="seconds; a frozen instrument is declared dead after 1.5x")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--username", help="the broker's user for this instrument")
    ap.add_argument("--password-env", help="the environment variable that holds its password")
    ap.add_argument("--ca", help="the CA certificate (PEM) of a broker that speaks TLS")
    asyncio.run(main(ap.parse_args()))
