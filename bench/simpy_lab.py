"""The same lab as a SimPy model: the baseline for the twin's virtual-time speed.

Same device types and instances, the same duration distributions, set-up and
clean times, failure and hang probabilities, deadlines, retries with back-off
and the same limit on experiments in the lab. No messages, no physics, no
journal: just the discrete-event skeleton.
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


def run(s, seed: int = 0) -> tuple[float, int, int]:
    """(lab hours, SimPy events, experiments done) of the scenario's campaign."""
    env = CountingEnvironment()
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
