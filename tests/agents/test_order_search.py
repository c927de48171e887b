"""campaign.local_search: a tabu search shortens a plan's device orders; the lab that follows them ends when the
search said, on labs it may search, and says why it did not search elsewhere."""

import logging
import statistics
import random
from pathlib import Path

import pytest
import torch

from agents.order_search import Shop, improve, shop_of
from agents.rl_scheduler import RlScheduler
from agents.rollout_plan import Plan, _search_orders
from twin import ScenarioError, jobshop_as_lab, random_jobshop
from twin.runtime.checks import check
from twin.runtime.lab import prepare, run
from twin.scenario.jobshop import read

ROOT = Path(__file__).resolve().parents[2]
POLICY = ROOT / "agents" / "policies" / "jobshop_scheduler.zip"
torch.set_num_threads(1)


@pytest.fixture(scope="module")
def shop():
    base = prepare(ROOT / "scenarios" / "jobshop.yaml")
    return jobshop_as_lab(base, random_jobshop(10, 6, 1, 99, random.Random("local-search:1")))


def ft06() -> tuple[Shop, dict[str, list[str]]]:
    """Fisher and Thompson's 6×6 shop (optimum 55), each machine taking its jobs in the reverse of their numbers:
    an order that is valid (no job waits on itself) and far from the best."""
    inst = read(ROOT / "scenarios" / "jobshop" / "ft06.txt")
    shop = Shop.of_jobs([[(f"e{j}s{k}", d) for k, (_, d) in enumerate(job)] for j, job in enumerate(inst.jobs)])
    orders: dict[str, list[str]] = {f"m{m}": [] for m in range(inst.machines)}
    for j in reversed(range(len(inst.jobs))):
        for k, (m, _) in enumerate(inst.jobs[j]):
            orders[f"m{m}"].append(f"e{j}s{k}")
    return shop, orders


def longest_path(shop: Shop, orders: dict[str, list[str]]) -> float:
    """The length of a schedule that starts every step once its job's and its device's previous steps end,
    computed here on its own (by repeated relaxation), not with the module's."""
    start = {t: 0.0 for t in shop.tasks}
    dur = dict(zip(shop.tasks, shop.duration))
    arcs = [(shop.tasks[i], shop.tasks[j]) for i, j in enumerate(shop.job_next) if j >= 0]
    arcs += [(a, b) for seq in orders.values() for a, b in zip(seq, seq[1:])]
    for _ in range(len(shop.tasks) + 1):
        moved = False
        for a, b in arcs:
            if start[a] + dur[a] > start[b]:
                start[b], moved = start[a] + dur[a], True
        if not moved:
            return max(start[t] + dur[t] for t in shop.tasks)
    raise AssertionError("the orders close a cycle")


def test_the_search_finds_ft06s_optimum_from_a_poor_order_and_keeps_every_step_on_its_device():
    shop, orders = ft06()
    found = improve(shop, orders, 3000, seed=0)
    assert found.start_length == longest_path(shop, orders) > 70
    assert found.length == longest_path(shop, found.orders) == 55
    assert {d: sorted(ts) for d, ts in found.orders.items()} == {d: sorted(ts) for d, ts in orders.items()}


def test_the_search_never_lengthens_and_repeats_for_a_seed():
    shop, orders = ft06()
    short = improve(shop, orders, 20, seed=3)
    assert short.length <= short.start_length and short.iterations == 20
    assert improve(shop, orders, 20, seed=3).orders == short.orders


def test_a_path_of_one_devices_work_is_the_shortest_only_where_no_other_device_could_take_it():
    shop = Shop.of_jobs([[(f"e{j}s0", 10)] for j in range(4)])  # four one-step jobs, all on m-1
    orders = {"m-1": ["e0s0", "e1s0", "e2s0", "e3s0"]}
    assert improve(shop, orders, 50).shortest
    twice = improve(shop, orders, 50, kinds={"m-1": "m", "m-2": "m"})  # a second m, idle: m-1's work could be shared
    assert not twice.shortest and twice.length == 40


def test_orders_that_close_a_cycle_are_refused():
    shop = Shop.of_jobs([[("e0s0", 1), ("e0s1", 1)], [("e1s0", 1), ("e1s1", 1)]])
    # m0 runs e0s1 before e1s0 and m1 e1s1 before e0s0: each job waits on the other
    with pytest.raises(ValueError, match="cycle"):
        improve(shop, {"m0": ["e0s1", "e1s0"], "m1": ["e1s1", "e0s0"]}, 10)


def test_the_lab_follows_the_searched_plan_to_the_lab_second_on_either_runtime(shop, tmp_path, capsys):
    searched = prepare(shop, overrides={"campaign.scheduler": f"rl:{POLICY}", "campaign.local_search": 3000})
    plan = RlScheduler(searched, str(POLICY)).follower.plan
    assert plan.rollouts == 1 and (plan.searched == 3000 or plan.shortest and 0 < plan.searched < 3000)
    assert plan.best_h < plan.played_h == plan.greedy_h  # the greedy run, shortened
    assert "the greedy run in the twin" in capsys.readouterr().err
    greedy = run(prepare(searched, overrides={"campaign.local_search": 0}), journal=tmp_path / "g.db")
    assert greedy.lab_hours == pytest.approx(plan.greedy_h)
    for runtime in ("auto", "asyncio"):  # auto: the fast runtime, the agent asked in-process
        followed = run(searched, journal=tmp_path / f"{runtime}.db", runtime=runtime)
        assert followed.lab_hours == pytest.approx(plan.best_h) and followed.done == 10
    assert plan.best_h * 3600 == pytest.approx(longest_path(shop_of(shop), plan.orders))


def test_after_rollouts_the_search_starts_from_the_best_run(shop, capsys):
    both = prepare(shop, overrides={"campaign.rollouts": 8, "campaign.local_search": 500})
    plan = RlScheduler(both, str(POLICY)).follower.plan
    alone = RlScheduler(prepare(both, overrides={"campaign.local_search": 0}), str(POLICY)).follower.plan
    assert plan.played_h == alone.best_h and plan.best_h <= alone.best_h
    assert "the best of 8 rollouts in the twin" in capsys.readouterr().err


@pytest.mark.parametrize("field, value", [("chemistry.stability_s", 100.0), ("campaign.max_in_flight", 4)])
def test_a_lab_that_is_not_a_job_shop_keeps_its_best_run_and_says_why(shop, field, value, caplog, capsys):
    lab = prepare(shop, overrides={field: value, "campaign.local_search": 500})
    with caplog.at_level(logging.WARNING, logger="agents.rollout_plan"):
        plan = RlScheduler(lab, str(POLICY)).follower.plan
    assert "a job shop only" in caplog.text and isinstance(plan.searched, str)
    assert plan.best_h == plan.greedy_h
    assert "campaign.local_search left out: it needs a job shop only" in capsys.readouterr().err


def test_set_up_and_cleaning_are_part_of_a_steps_time_and_the_lab_still_ends_when_the_search_said(shop, tmp_path):
    """A step's set-up and cleaning keep its device, and its sample goes on only after both: the search's
    durations include them (a shop with them is not played backwards, but it is searched)."""
    lab = prepare(shop, overrides={"devices.m0.setup_s": 7.0, "devices.m2.clean_s": 11.0,
                                   "campaign.scheduler": f"rl:{POLICY}", "campaign.local_search": 2000})
    plan = RlScheduler(lab, str(POLICY)).follower.plan
    assert isinstance(plan.searched, int) and plan.best_h < plan.played_h
    for runtime in ("auto", "asyncio"):
        assert run(lab, journal=tmp_path / f"{runtime}.db", runtime=runtime).lab_hours == pytest.approx(plan.best_h)


def test_steps_shorter_than_their_models_leave_the_plan_as_played(shop, caplog):
    """A driver whose steps end sooner than its duration model says: the search's lengths would not be the lab's."""
    orders = RlScheduler(prepare(shop, overrides={"campaign.rollouts": 2}), str(POLICY)).follower.plan.orders
    played = Plan(orders, 1, 1.0, 1.0, 0.01, 0.01, 0.0)  # a run of 36 lab-s: far shorter than the models say
    with caplog.at_level(logging.WARNING, logger="agents.rollout_plan"):
        _search_orders(played, prepare(shop, overrides={"campaign.local_search": 100}), job_shop=True, seed=0)
    assert played.orders == orders and "duration models" in caplog.text and isinstance(played.searched, str)


def test_a_rule_asked_to_search_is_refused_naming_the_field(shop):
    s = prepare(shop, overrides={"campaign.scheduler": "mwkr", "campaign.local_search": 100})
    with pytest.raises(ScenarioError, match="campaign.local_search: 100: only the rl scheduler plays a lab ahead") \
            as exc:
        check(s)
    assert "set campaign.local_search: 0" in str(exc.value)


def test_a_long_search_says_how_far_it_has_got(shop, monkeypatch, capsys):
    from agents import rollout_plan

    monkeypatch.setattr(rollout_plan, "HEARTBEAT_S", 0.0)
    RlScheduler(prepare(shop, overrides={"campaign.local_search": 1000, "campaign.seed": 1}), str(POLICY))
    told = [line for line in capsys.readouterr().err.splitlines() if " swaps tried, the shortest plan so far " in line]
    swaps = [int(line.split()[1].replace(",", "")) for line in told]
    shortest = [int(line.split("so far ")[1].split()[0].replace(",", "")) for line in told]
    assert len(told) >= 3 and swaps == sorted(swaps) and shortest == sorted(shortest, reverse=True)
    assert all(line.startswith("rl: ") and line.endswith(" s so far") and " of 1,000 swaps" in line for line in told)


def shops():
    """Small shops of any form a file may hold: jobs that visit a device twice, even back to back, steps of no
    length, a job of one step; and a valid order for each (a random list schedule's), as (shop, orders)."""
    from hypothesis import strategies as st

    step = st.tuples(st.integers(0, 3), st.sampled_from([0, 0, 1, 2, 5, 9]))
    return st.tuples(st.lists(st.lists(step, min_size=1, max_size=6), min_size=1, max_size=6), st.randoms())


def list_schedule(jobs: list[list[tuple[int, float]]], rng: random.Random) -> dict[str, list[str]]:
    """Each device's order in a run that starts, at random, any job's next step: an order no job waits on itself in."""
    nxt = [0] * len(jobs)
    orders: dict[str, list[str]] = {}
    while any(k < len(job) for k, job in zip(nxt, jobs)):
        j = rng.choice([j for j, job in enumerate(jobs) if nxt[j] < len(job)])
        orders.setdefault(f"m{jobs[j][nxt[j]][0]}", []).append(f"e{j}s{nxt[j]}")
        nxt[j] += 1
    return orders


def test_on_any_small_shop_the_search_keeps_a_plan_the_lab_can_follow_and_never_a_longer_one():
    from hypothesis import given, settings

    @settings(max_examples=300, deadline=None)
    @given(shops())
    def check_one(drawn):
        jobs, rng = drawn
        shop = Shop.of_jobs([[(f"e{j}s{k}", d) for k, (_, d) in enumerate(job)] for j, job in enumerate(jobs)])
        orders = list_schedule(jobs, rng)
        found = improve(shop, orders, 200, seed=rng.randrange(100))
        assert found.start_length == longest_path(shop, orders)
        assert found.length == longest_path(shop, found.orders) <= found.start_length
        assert {d: sorted(ts) for d, ts in found.orders.items()} == {d: sorted(ts) for d, ts in orders.items()}
        if found.shortest:  # a lower bound: some device's work, or some job's
            loads: dict[int, float] = {}
            for job in jobs:
                for m, d in job:
                    loads[m] = loads.get(m, 0) + d
            assert found.length == max(*loads.values(), *(sum(d for _, d in job) for job in jobs))

    check_one()


def test_a_plan_that_is_one_devices_work_says_it_is_the_shortest(tmp_path, capsys):
    """A shop whose greedy run already takes exactly its busiest device's work: the search stops at once."""
    (tmp_path / "shop.txt").write_text("3 3\n0 5 0 3 1 4\n1 2 2 0 0 6\n2 4 1 3 1 2\n")  # m0's work: 14
    lab = prepare(ROOT / "scenarios" / "jobshop.yaml", overrides={"jobshop.file": str(tmp_path / "shop.txt"),
                                                                  "campaign.local_search": 1000})
    plan = RlScheduler(lab, str(POLICY)).follower.plan
    assert plan.best_h * 3600 == pytest.approx(14) and plan.shortest and plan.searched == 0
    told = capsys.readouterr().err
    assert "14 lab-s as played, then 0 tabu-search swaps on its orders (the shortest plan there is: its longest " \
           "path is one job's work, or one device's with no other of its type), takes 14 lab-s against the greedy " \
           "run's 14 lab-s" in told


def test_a_bench_says_which_rows_are_plans_played_ahead(tmp_path):
    """`twin bench schedulers … --set campaign.local_search=N` printed the rl row's 1.5 % beside MWKR's 24.7 % with
    nothing on stdout saying that the row was a searched plan, not the policy deciding as the lab went."""
    import json

    from tests.conftest import twin_cli

    args = ["bench", "schedulers", str(ROOT / "scenarios" / "jobshop.yaml"), "--jobshop", "jobshop/la02.txt",
            "--schedulers", f"mwkr,rl:{POLICY}"]
    searched = twin_cli(*args, "--set", "campaign.local_search=300", columns=80)
    assert searched.exit_code == 0, searched.output
    said = " ".join(searched.stdout.split())
    assert ("rl:jobshop_scheduler: the lab played ahead in the twin (campaign.local_search: 300) and the plan "
            "followed, not the policy deciding as the lab goes; the rules ran as they go") in said, said
    greedy = twin_cli(*args, "--json", columns=80)
    assert json.loads(greedy.stdout)["labs"][0]["played_ahead"] == ""
    assert "played ahead" not in " ".join(twin_cli(*args, columns=80).stdout.split())


@pytest.mark.process
@pytest.mark.parametrize("stop, code, said", [("int", 130, "interrupted"), ("term", 143, "terminated (SIGTERM)")])
@pytest.mark.parametrize("command", ["run", "serve"])
def test_a_command_stopped_while_its_scheduler_plans_says_so_and_leaves_nothing(tmp_path, command, stop, code, said):
    """Ctrl-C or SIGTERM during a long plan (campaign.local_search) ended `twin run` and `twin scheduler serve` with
    130 or 143 and not a word."""
    import os
    import signal
    import subprocess
    import sys
    import time

    if command == "run":
        args = ["run", str(ROOT / "scenarios" / "jobshop.yaml"), "--set", "jobshop.file=jobshop/ft10.txt",
                "--scheduler", f"rl:{POLICY}", "--set", "campaign.local_search=1000000"]
        says = "while the lab was being checked and its scheduler planned it ahead: nothing ran, and no journal was"
    else:
        lab = tmp_path / "lab.yaml"
        lab.write_text(f"name: shop\nlab: shop\njobshop: {{file: {ROOT / 'scenarios' / 'jobshop' / 'ft10.txt'}}}\n"
                       "campaign: {scheduler: remote, local_search: 1000000}\n")
        args = ["scheduler", "serve", str(lab), "--scheduler", f"rl:{POLICY}", "--connect", "tcp/127.0.0.1:9"]
        says = "before it served (joining the lab, or its scheduler planning the lab ahead): nothing was served"
    proc = subprocess.Popen([sys.executable, "-m", "twin", *args], cwd=tmp_path, stderr=subprocess.PIPE,
                            stdout=subprocess.DEVNULL, text=True, env={**os.environ, "COLUMNS": "200"})
    first = proc.stderr.readline()  # the planning has begun
    assert first.startswith("rl: playing"), first
    time.sleep(0.5)
    proc.send_signal(signal.SIGINT if stop == "int" else signal.SIGTERM)
    rest = proc.communicate(timeout=60)[1]
    assert proc.returncode == code, rest
    assert f"{said} {says}" in " ".join(rest.split()), rest
    assert not list(tmp_path.rglob("*.db"))


def test_the_paths_kept_up_to_date_swap_by_swap_equal_the_paths_computed_afresh():
    """The search updates each step's earliest start and the path after it as it swaps, instead of computing them
    all again each time: after every swap they must equal a fresh computation, and a swap it refuses as closing a
    cycle must be one that does."""
    from hypothesis import given, settings

    from agents.order_search import _Orders

    @settings(max_examples=150, deadline=None)
    @given(shops())
    def check_one(drawn):
        jobs, rng = drawn
        shop = Shop.of_jobs([[(f"e{j}s{k}", d) for k, (_, d) in enumerate(job)] for j, job in enumerate(jobs)])
        index = {t: i for i, t in enumerate(shop.tasks)}
        kept = _Orders(shop, [[index[t] for t in seq] for seq in list_schedule(jobs, rng).values()])
        for _ in range(30):
            pairs = [(seq[p], seq[p + 1]) for seq in kept.seqs for p in range(len(seq) - 1)]
            if not pairs:
                return
            u, v = rng.choice(pairs)
            swapped = [list(seq) for seq in kept.seqs]
            for seq in swapped:
                if u in seq:
                    p = seq.index(u)
                    seq[p], seq[p + 1] = v, u
            fresh = _Orders(shop, swapped)
            if kept.swap(u, v):
                assert fresh.acyclic and (kept.head, kept.tail, kept.length) == (fresh.head, fresh.tail, fresh.length)
                assert kept.seqs == fresh.seqs
            else:
                assert not fresh.acyclic

    check_one()


def test_a_lab_whose_every_experiment_is_abandoned_is_planned_without_a_crash_and_the_search_says_why(shop, capsys):
    """A lab whose experiments the planner's checks all refuse (a parameter no proposal gives) asks no decision:
    playing it ahead crashed on a view it never had ('NoneType' object has no attribute 'now')."""
    refused = prepare(shop, overrides={"chemistry.parameters": {"strength": {"low": 0, "high": 1}}})
    assert RlScheduler(prepare(refused, overrides={"campaign.rollouts": 4}), str(POLICY)).follower.plan.best_h == 0
    plan = RlScheduler(prepare(refused, overrides={"campaign.local_search": 100}), str(POLICY)).follower.plan
    assert isinstance(plan.searched, str) and "the best run started 0 of the shop's 60" in plan.searched
    assert "campaign.local_search left out: it needs a run that started every step" in capsys.readouterr().err


def test_a_labs_typical_step_on_fixed_routes_is_what_its_devices_take(tmp_path):
    """A lab of fixed routes whose steps last what their devices' duration models say (not a job-shop file's
    `duration_s`) had a typical step of 1e-6 lab-s: every time feature the policy reads was scaled by it, and a
    scaled clock warned of steps of "0.0 lab-s"."""
    import yaml

    from twin.scenario.objective import typical_step

    routes = [{"params": {"extra_s": 10}, "route": [{"step": "bake", "device": "oven"}, {"step": "look", "device": "camera"}]},
              {"params": {"extra_s": 0}, "route": [{"step": "bake", "device": "oven", "params": {"extra_s": 30}}]}]
    (tmp_path / "lab.yaml").write_text(yaml.safe_dump({
        "name": "bakery", "lab": "bakery",
        "devices": {"oven": {"driver": "machine", "steps": ["bake"], "setup_s": 4,
                             "duration": {"mean_s": 20, "cv": 0, "plus_param": "extra_s"}},
                    "camera": {"driver": "machine", "steps": ["look"], "duration": {"mean_s": 6, "cv": 0}}},
        "workflow": [{"step": "bake", "device": "oven"}],
        "chemistry": {"model": "none", "parameters": {"extra_s": {"low": 0, "high": 100}}},
        "campaign": {"planner": "fixed", "budget": 2, "max_in_flight": 2, "planner_options": {"proposals": routes}}}))
    assert typical_step(prepare(tmp_path / "lab.yaml")) == pytest.approx((34 + 6 + 54) / 3)  # 20+4+10; 6; 20+4+30
    assert typical_step(prepare(ROOT / "scenarios" / "jobshop.yaml")) == pytest.approx(
        statistics.mean(d for job in read(ROOT / "scenarios" / "jobshop" / "ft06.txt").jobs for _, d in job))
