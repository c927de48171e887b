"""The range a shipped candidate policy sees, recorded in its policy file (``observed``) after the fact.

``twin train`` records it as it judges each policy it keeps (``agents.train_scheduler.Judge``); a policy saved
before that did not. This replays the same judgement — the scenario on the evaluation seeds and 40 labs held
out from its ``training`` ranges, greedy — and adds what the policy saw to its ``.json``:

    python -m agents.observed_range agents/policies/jobshop_scheduler.zip scenarios/jobshop.yaml
"""

from __future__ import annotations

import sys
from pathlib import Path

from agents.candidates import CandidateEncoder, Observed
from agents.rl_scheduler import RlScheduler
from agents.judging import EVAL_SEEDS, campaign, held_out_labs
from twin import Scenario, prepare, read_meta, write_description


def observe(policy: Path, scenario: Scenario, held_out_count: int = 40) -> dict:
    """What ``policy`` sees over the scenario's evaluation seeds and ``held_out_count`` held-out labs (more than
    the Judge's 6–24: this range stands in for what training saw too), as its file records it."""
    agent = RlScheduler(scenario, str(policy))
    encoding = read_meta(policy)["signature"]["encoding"]
    seen = Observed(agent.encoder.width)
    for lab, seeds in [(scenario, EVAL_SEEDS), *[(lab, (0,)) for lab in held_out_labs(scenario, held_out_count)]]:
        agent.encoder = CandidateEncoder(lab, encoding)  # as it was judged: unheld
        agent.encoder.seen = seen
        for seed in seeds:
            campaign(lab, seed, agent.decide)
    observed = seen.to_meta()
    if observed is None:
        raise ValueError(f"{policy}: it never saw a candidate on {scenario.name}'s labs")
    return observed


def main(argv: list[str]) -> None:
    policy, scenario = Path(argv[0]), prepare(argv[1])
    meta = read_meta(policy)
    meta["observed"] = observe(policy, scenario)
    write_description(policy, meta)
    print(f"{policy.with_suffix('.json')}: observed range of {len(meta['observed']['rows'][0])} row columns and "
          f"{len(meta['observed']['globals'][0])} globals over {scenario.name}'s evaluation labs")


if __name__ == "__main__":
    main(sys.argv[1:])
