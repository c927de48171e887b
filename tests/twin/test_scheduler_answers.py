"""What a scheduler or planner plugin answers, read inside its cover: an answer that raises as it is read (a
generator), or that is an awaitable, is the fallback rule's decision (a planner's failure), never a traceback; and
``async def decide``/``propose`` are refused when the plugin is loaded."""

import pytest

from tests.conftest import qd_lab
from twin.campaign.journal_read import read_events
from twin.runtime.lab import run
from twin.scenario import parse


class GeneratorThatRaises:
    """Answers a generator, whose code (and its error) runs only as the campaign reads the answer."""

    def decide(self, view):
        yield from ()
        raise ValueError("inside the generator")


class AwaitableAnswer:
    """A plain ``def`` that answers a coroutine (a helper of an async library, say)."""

    def decide(self, view):
        import asyncio

        return asyncio.sleep(0, result=[])


class AsyncDecide:
    async def decide(self, view):
        return []


class AsyncPropose:
    async def propose(self, n, history, pending):
        return []


@pytest.mark.parametrize("runtime", ["auto", "asyncio"])
def test_an_answer_that_fails_as_it_is_read_or_is_an_awaitable_is_covered_by_the_fallback_rule(tmp_path, runtime):
    """A generator raising as the campaign read it ended the campaign with a traceback on both runtimes; a
    coroutine did so on the asyncio runtime, and on the fast one stopped the run with "run with --runtime asyncio"
    (and Python's "never awaited" warning)."""
    import gc
    import warnings

    for name, says in (("GeneratorThatRaises", "raised ValueError('inside the generator')"),
                       ("AwaitableAnswer", "answered an awaitable (coroutine): decide() must answer at once")):
        lab = parse(qd_lab(**{"campaign.scheduler": f"tests.twin.test_scheduler_answers:{name}", "campaign.budget": 3}))
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            summary = run(lab, journal=tmp_path / f"{name}.db", runtime=runtime)
            gc.collect()
        assert summary.done == 3 and summary.scheduler_fallbacks == summary.decisions > 0, name
        said = [e["detail"] for e in read_events(tmp_path / f"{name}.db", "scheduler.fallback")]
        assert len(said) == 1 and says in said[0], said
        assert not [w for w in caught if "never awaited" in str(w.message)], name


def test_an_async_decide_or_propose_is_refused_when_it_is_loaded():
    """`async def decide` crashed a campaign on the asyncio runtime when it raised; `async def propose` was taken
    and the campaign ended with nothing proposed."""
    from twin.core import plugins
    from twin.core.errors import PluginError

    here = "tests.twin.test_scheduler_answers"
    with pytest.raises(PluginError, match=r"AsyncDecide': decide\(\) is `async def`, and the lab takes a scheduler's "
                                          r"answer at once: make it a plain `def`; .*\(campaign.scheduler: remote"):
        plugins.load("schedulers", f"{here}:AsyncDecide")
    with pytest.raises(PluginError, match=r"AsyncPropose': propose\(\) is `async def`, .* make it a plain `def`"):
        plugins.load("planners", f"{here}:AsyncPropose")
