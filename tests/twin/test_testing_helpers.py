"""The helpers a driver's own tests use (docs/drivers.md): run_step follows the duration it is given."""

from twin import StepResult, driver_setup, run_step


class Timed:
    capabilities = frozenset({"measure"})

    def __init__(self, setup):
        pass

    async def run(self, step, params, sample, ctx):
        await ctx.clock.sleep(ctx.draw_duration(params))
        return StepResult({"ok": 1}, sample)

    async def safe_state(self):
        pass


def test_run_step_takes_the_duration_of_the_setup_it_is_given():
    setup = driver_setup("timed-1", mean_s=240.0)
    _, took = run_step(Timed(setup), "measure", {}, None, setup=setup)
    assert took == 240.0
    assert run_step(Timed(setup), "measure", {}, None, mean_s=15.0)[1] == 15.0
    assert run_step(Timed(setup), "measure", {}, None)[1] == 60.0
