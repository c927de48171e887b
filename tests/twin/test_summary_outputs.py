"""What a summary shows of the best experiment's outputs, whatever a driver measured them as."""

import io

import numpy as np
from rich.console import Console

from tests.conftest import qd_lab
from twin import StepResult
from twin.runtime.lab import run
from twin.scenario import parse
from twin.view.report import render_summary


class Inspecting:
    """A spectrometer that also says whether the cell was clear (a bool, numpy's or Python's) and its phase."""

    capabilities = frozenset({"measure"})

    def __init__(self, setup):
        pass

    async def run(self, step, params, sample, ctx):
        await ctx.clock.sleep(60)
        return StepResult({"peak_nm": np.float64(sample["peak_nm"]), "clear": np.bool_(True), "wet": False,
                           "phase": "rocksalt", "replicates": np.int64(3)}, sample)

    async def safe_state(self):
        pass


def test_a_drivers_yes_no_outputs_read_as_such_and_its_numbers_as_numbers(tmp_path):
    s = run(parse(qd_lab(**{"devices.spectrometer.driver": "tests.twin.test_summary_outputs:Inspecting",
                            "campaign.budget": 3, "campaign.stop_on_target": False})), journal=tmp_path / "j.db")
    out = io.StringIO()
    render_summary(s, Console(file=out, width=300))
    best = [line for line in out.getvalue().splitlines() if "— experiment" in line]
    assert best and all("clear=true" in line and "wet=false" in line and "replicates=3" in line for line in best), best
    assert all("peak_nm=" in line and "phase" not in line for line in best), best  # words are not a measure's row


def test_a_count_of_one_is_said_in_the_singular(tmp_path):
    """"1 device losses", "1 decisions": each count in the summary takes the noun its number takes."""
    import dataclasses

    from twin.campaign.summary import losses_text, quarantines_text, summary_markdown

    s = run(parse(qd_lab(**{"campaign.budget": 1})), journal=tmp_path / "j.db")
    ones = dataclasses.replace(s, devices_lost=1, steps_lost=1, quarantines=1, invalid_messages=1, late_results=1,
                               rejected_messages=1, presence_flaps=1, decisions=1)
    out = io.StringIO()
    render_summary(ones, Console(file=out, width=300))
    text = " ".join(out.getvalue().split())
    for said in ("1 device loss (1 running step lost with them), 1 quarantine, 1 invalid message, 1 late result",
                 "1 message without the attempt's provenance (message.rejected), 1 presence flap", "1 decision, "):
        assert said in text, text
    assert losses_text(2, 3) == "2 device losses (3 running steps lost with them)" and losses_text(0, 0) == \
        "0 device losses"
    assert quarantines_text(0, 0) == "0 quarantines"
    assert "| faults | 1 device loss (1 running step lost with them), 1 quarantine |" in summary_markdown(
        {**s.to_dict(), "devices_lost": 1, "steps_lost": 1, "quarantines": 1})
