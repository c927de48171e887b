"""A workflow step's own parameters reach its driver with the experiment's, and win a clash."""

import json

from tests.conftest import qd_lab
from twin import DriverSetup, StepContext, StepResult
from twin.campaign.journal_read import read_events
from twin.runtime.lab import run
from twin.scenario import parse


class Echo:
    capabilities = frozenset({"measure"})

    def __init__(self, setup: DriverSetup) -> None:
        pass

    async def run(self, step: str, params: dict, sample: dict | None, ctx: StepContext) -> StepResult:
        await ctx.clock.sleep(ctx.draw_duration(params))
        return StepResult({"seen": json.dumps(params, sort_keys=True)}, sample)

    async def safe_state(self) -> None:
        pass


def test_workflow_step_params_reach_the_driver(tmp_path):
    lab = qd_lab(**{"devices.spectrometer.driver": "tests.twin.test_workflow_params:Echo", "campaign.budget": 2,
                    "workflow": [{"step": "synthesise", "device": "synthesiser"},
                                 {"step": "measure", "device": "spectrometer",
                                  "params": {"gain": 2.5, "mode": "fast", "temperature_c": -1}}]})
    summary = run(parse(lab), journal=tmp_path / "j.db")
    assert summary.done == 2
    rows = [e for e in read_events(tmp_path / "j.db", "msg.result") if e["device"].startswith("spectrometer")]
    assert len(rows) == 2
    for e in rows:
        seen = json.loads(json.loads(e["detail"])["body"]["outputs"]["seen"])
        assert seen["gain"] == 2.5 and seen["mode"] == "fast"
        assert seen["temperature_c"] == -1  # the step's own value wins over the experiment's
        assert 10 <= seen["time_s"] <= 600  # and the experiment's other parameters are there
