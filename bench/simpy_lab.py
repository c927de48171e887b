"""The same lab as a SimPy model: the baseline for the twin's virtual-time speed.

Same device types and instances, the same duration distributions, set-up and
clean times, failure and hang probabilities, deadlines, retries with back-off
and the same limit on experiments in the lab. No messages and no journal.

``physics=False``: the bare discrete-event skeleton. ``physics=True``: every
step also calls the scenario's own driver (the same physics, noise and
fitting the twin's devices run), on a stepped clock, and takes the lab time
the driver slept: the same modelled work as the twin, so the ratio compares
like with like.
"""

from __future__ import annotations

import math
import random

import simpy


class CountingEnvironment(simpy.Environment):
    events = 0

    def step(self) -> None:
        self.events += 1
        super().step()


def _physics(s, seed: int):
    """Call a step's driver on a stepped clock: its outputs, and the lab seconds it slept."""
    from twin.core.streams import seeded
    from twin.device.driver import StepContext
    from twin.runtime.assembly import load_driver
    from twin.learning.workcell import SteppedClock, _complete

    drivers = {d: load_driver(s, d, f"{d}-simpy") for d in s.devices}
    rngs = {d: seeded(seed, "simpy", d)[1] for d in s.devices}
    clock = SteppedClock()

    def step(ws, params, sample):
        spec = s.devices[ws.device]
        ctx = StepContext(clock=clock, rng=rngs[ws.device], duration=spec.duration,
                          progress=lambda *_: None, telemetry=lambda _: None)
        t0 = clock.t
        result = _complete(drivers[ws.device].run(ws.step, params, sample, ctx), ws.device)
        return result, clock.t - t0

    return clock, step


def run(s, seed: int = 0, physics: bool = False) -> tuple[float, int, int]:
    """(lab hours, SimPy events, experiments done) of the scenario's campaign."""
    env = CountingEnvironment()
    clock, call = _physics(s, seed) if physics else (None, None)
    rng = random.Random(seed)
    pools = {name: simpy.Resource(env, capacity=spec.instances) for name, spec in s.devices.items()}
    slots = simpy.Resource(env, capacity=s.campaign.max_in_flight)
    o = s.orchestrator
    done = [0]

    def draw(spec, params) -> float:
        d = spec.duration
        base = d.mean_s
        if base > 0 and d.cv > 0:
            sigma = math.sqrt(math.log(1 + d.cv**2))
            base = rng.lognormvariate(math.log(base) - sigma**2 / 2, sigma)
        return base + (params.get(d.plus_param, 0.0) if d.plus_param else 0.0)

    def experiment(params):
        sample = None
        with slots.request() as slot:
            yield slot
            for ws in s.workflow:
                spec = s.devices[ws.device]
                for attempt in range(1, o.retry.max_attempts + 1):
                    with pools[ws.device].request() as req:
                        yield req
                        hang = rng.random() < spec.faults.hang_p
                        fail = rng.random() < spec.faults.fail_p
                        extra = params.get(spec.duration.plus_param, 0.0) if spec.duration.plus_param else 0.0
                        expected = spec.duration.mean_s + extra + spec.setup_s + spec.clean_s
                        deadline = expected * o.timeout_factor + o.timeout_slack_s
                        if call is not None:
                            clock.t = env.now + spec.setup_s  # the sample ages in lab time
                            result, took = call(ws, params, sample)
                            sample = result.sample if result.sample is not None else sample
                            busy = spec.setup_s + took + spec.clean_s
                        else:
                            busy = spec.setup_s + draw(spec, params) + spec.clean_s
                        yield env.timeout(deadline if hang or busy > deadline else busy)
                        ok = not (hang or fail or busy > deadline)
                    if ok:
                        break
                    if attempt == o.retry.max_attempts:
                        return
                    backoff = min(o.retry.backoff_max_s, o.retry.backoff_s * 2 ** (attempt - 1))
                    yield env.timeout(backoff * (1 + o.retry.jitter * (2 * rng.random() - 1)))
            done[0] += 1

    box = s.chemistry.parameters
    for _ in range(s.campaign.budget):
        env.process(experiment({k: rng.uniform(p.low, p.high) for k, p in box.items()}))
    env.run()
    return env.now / 3600, env.events, done[0]
