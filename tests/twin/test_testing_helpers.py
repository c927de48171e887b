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


class TimedWithoutParams(Timed):
    async def run(self, step, params, sample, ctx):
        await ctx.clock.sleep(ctx.draw_duration())
        return StepResult({"ok": 1}, sample)


def test_draw_duration_needs_the_params_only_for_a_duration_that_adds_one():
    """`ctx.draw_duration()` without params failed every step with a TypeError (missing argument), though only a
    duration with plus_param reads them."""
    import dataclasses

    import pytest

    from twin.scenario import Duration

    setup = driver_setup("timed-1", mean_s=240.0)
    assert run_step(TimedWithoutParams(setup), "measure", {}, None, setup=setup)[1] == 240.0
    soak = dataclasses.replace(setup, duration=Duration(mean_s=240.0, cv=0.0, plus_param="time_s"))
    assert run_step(Timed(soak), "measure", {"time_s": 60.0}, None, setup=soak)[1] == 300.0
    with pytest.raises(TypeError, match=r"draw_duration\(\) needs the step's params: this device type's duration "
                                        r"adds the parameter 'time_s' \(duration.plus_param\); call "
                                        r"ctx.draw_duration\(params\)"):
        run_step(TimedWithoutParams(soak), "measure", {"time_s": 60.0}, None, setup=soak)
