"""CP-SAT (OR-Tools, the optional ``bench`` extra) on scheduling problems: the offline bound, and the online rival.

``solve`` takes operations grouped in jobs (each job's operations run in
order) on device types with a number of identical instances each, some of
them possibly busy until a known time, and minimises the makespan. A job
shop is the special case of one instance per type and every job ready at 0.

Such a model always has a schedule, and CP-SAT finds one in milliseconds when it has the CPU; on a machine too busy
to give it any within its time, the solve is tried again with twice the time, up to ``TRIES`` times in all, before
it fails.

A time limit in wall seconds ends a solve wherever the CPU it got left it: the same model may end with another
plan on a busier machine. ``work_limit`` ends it after an amount of CP-SAT's own deterministic work instead (its
``max_deterministic_time``; roughly 0.15 of a unit a second on one core of the machine these notes were written
on), and one thread so stopped ends with the same plan on any machine under any load.
"""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class Op:
    device_type: str
    duration: int
    release: int = 0  # may not start before (lab seconds from now)


@dataclass
class Solution:
    makespan: int
    optimal: bool
    starts: list[list[int]]  # per job, per operation


#: solves of a model before it fails, each with twice the time of the one before
TRIES = 4


def solve(jobs: list[list[Op]], capacity: dict[str, int], time_limit_s: float = 10.0, workers: int = 2,
          busy: dict[str, list[int]] | None = None, left_shift: bool = False,
          work_limit: float | None = None, tries: int = TRIES) -> Solution:
    """Minimum makespan; ``busy[type]`` lists when each busy instance of ``type`` frees up.

    ``left_shift`` also minimises the sum of start times (below the makespan), so that
    operations off the critical path start as early as they can. ``tries``: how many solves, each with twice the
    time, before it fails (1: ``time_limit_s`` is all it takes).
    """
    try:
        from ortools.sat.python import cp_model
    except ImportError as exc:
        import importlib.util

        if importlib.util.find_spec("ortools") is not None:  # installed, and its import broke (a Ctrl-C amid it)
            raise
        raise ImportError("CP-SAT needs OR-Tools: pip install -e '.[bench]'") from exc
    model = cp_model.CpModel()
    horizon = sum(op.duration for job in jobs for op in job) + max(
        [op.release for job in jobs for op in job] + [t for ts in (busy or {}).values() for t in ts] + [0]) + 1
    starts, ends, per_type = [], [], {t: [] for t in capacity}
    for j, job in enumerate(jobs):
        row, prev_end = [], None
        for k, op in enumerate(job):
            s = model.new_int_var(op.release, horizon, f"s{j}_{k}")
            e = model.new_int_var(0, horizon, f"e{j}_{k}")
            per_type[op.device_type].append(model.new_interval_var(s, op.duration, e, f"i{j}_{k}"))
            if prev_end is not None:
                model.add(s >= prev_end)
            row.append(s)
            prev_end = e
        starts.append(row)
        if prev_end is not None:
            ends.append(prev_end)
    for dtype, intervals in per_type.items():
        frees = (busy or {}).get(dtype, [])
        fixed = [model.new_fixed_size_interval_var(0, max(t, 1), f"busy_{dtype}_{i}") for i, t in enumerate(frees) if t > 0]
        if capacity[dtype] == 1:
            model.add_no_overlap(intervals + fixed)
        else:
            model.add_cumulative(intervals + fixed, [1] * (len(intervals) + len(fixed)), capacity[dtype])
    makespan = model.new_int_var(0, horizon, "makespan")
    model.add_max_equality(makespan, ends or [model.new_constant(0)])
    if left_shift:
        firsts = [row[0] for row in starts if row]
        model.minimize(makespan * (len(firsts) * horizon + 1) + sum(firsts))
    else:
        model.minimize(makespan)
    solver = cp_model.CpSolver()
    solver.parameters.num_workers = workers
    solver.parameters.catch_sigint_signal = False  # its own handler left Ctrl-C killing `twin train` unannounced
    given = 0.0
    for attempt in range(tries):
        solver.parameters.max_time_in_seconds = time_limit_s * 2 ** attempt
        if work_limit is not None:
            solver.parameters.max_deterministic_time = work_limit * 2 ** attempt
        given += solver.parameters.max_time_in_seconds
        status = solver.solve(model)
        if status in (cp_model.OPTIMAL, cp_model.FEASIBLE):
            break
    else:
        raise RuntimeError(f"CP-SAT found no schedule in {tries} {'try' if tries == 1 else 'tries'} ({given:g} s of "
                           f"wall time in all"
                           f"{'' if work_limit is None else f', {work_limit * (2 ** tries - 1):g} units of work'}): "
                           "the machine gave it no CPU, or the model is far larger than a lab's")
    return Solution(int(solver.value(makespan)), status == cp_model.OPTIMAL,
                    [[int(solver.value(s)) for s in row] for row in starts])


def jobshop(jobs: list[list[tuple[int, int]]], machines: int, time_limit_s: float = 60.0,
            workers: int = 2, work_limit: float | None = None) -> Solution:
    """A job-shop instance (per job: (machine, duration) in order), machines numbered 0..machines-1."""
    return solve([[Op(f"m{m}", d) for m, d in job] for job in jobs], {f"m{m}": 1 for m in range(machines)},
                 time_limit_s, workers, work_limit=work_limit)
