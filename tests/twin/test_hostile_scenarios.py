"""Scenario files are hostile input: every malformed file gets a clear error from `twin validate` itself.

The cases are generated from the shipped scenarios (each mutation applied to
every scenario it makes sense for) plus whole-file attacks. Each asserts the
error names the file and the field (or line) and that nothing else happens:
no other exception, no hang (a per-case time limit), bounded text.
"""

import copy
import signal
import subprocess
import sys
from pathlib import Path

import pytest
import yaml

from twin.core.errors import TwinError
from twin.runtime.checks import validate_file

ROOT = Path(__file__).resolve().parents[2]
SHIPPED = ["quantum_dots", "flaky_lab", "catalyst", "bandgap", "mqtt_lab"]
LIMIT_S = 5


def shipped(name):
    return yaml.safe_load((ROOT / "scenarios" / f"{name}.yaml").read_text())


def first_device(raw):
    return next(iter(raw["devices"]))


def first_param(raw):
    return next(iter(raw["chemistry"]["parameters"]))


def setter(path_fn, value):
    """A mutation that sets the field ``path_fn(raw)`` (a dotted path) to ``value``."""
    def mutate(raw):
        node, *_ = [raw]
        *parents, leaf = path_fn(raw).split(".")
        for p in parents:
            node = node[int(p)] if isinstance(node, list) else node.setdefault(p, {})
        node[leaf] = value
    return mutate


def dev(field):
    return lambda raw: f"devices.{first_device(raw)}.{field}"


def rename_first_device(new):
    def mutate(raw):
        old = first_device(raw)
        raw["devices"] = {new if k == old else k: v for k, v in raw["devices"].items()}
        for w in raw["workflow"]:
            if w["device"] == old:
                w["device"] = new
    return mutate


def duplicate_target(raw):
    raw["chemistry"]["targets"].append(copy.deepcopy(raw["chemistry"]["targets"][0]))


def unknown_output_target(raw):
    raw["chemistry"]["targets"] = [{"name": "X", "outputs": {"nothing_makes_this": {"min": 1}}}]


def min_over_max(raw):
    raw["chemistry"]["targets"] = [{"name": "X", "outputs": {next(iter(raw["chemistry"]["targets"][0]["outputs"])):
                                                             {"min": 10, "max": 1}}}]


def colliding_instances(raw):
    d = first_device(raw)
    raw["devices"][d]["instances"] = 2
    raw["devices"][f"{d}-1"] = copy.deepcopy(raw["devices"][d])
    raw["devices"][f"{d}-1"]["instances"] = 1


def negative_plus_param(raw):
    d = first_device(raw)
    p = first_param(raw)
    raw["chemistry"]["parameters"][p] = {"low": -100, "high": 10}
    raw["devices"][d]["duration"]["plus_param"] = p


def unknown_plus_param(raw):
    raw["devices"][first_device(raw)]["duration"]["plus_param"] = "no_such_parameter"


def empty_box(raw):
    raw["chemistry"]["parameters"] = {}


def inf_box(raw):
    raw["chemistry"]["parameters"][first_param(raw)] = {"low": 0, "high": float("inf")}


def huge_box(raw):
    raw["chemistry"]["parameters"][first_param(raw)] = {"low": -1e300, "high": 1e300}


# (id, mutation, words the error must contain)
MUTATIONS = [
    ("inf-duration", setter(dev("duration.mean_s"), float("inf")), "duration.mean_s"),
    ("huge-duration", setter(dev("duration.mean_s"), 1e300), "duration.mean_s"),
    ("negative-duration", setter(dev("duration.mean_s"), -5), "duration.mean_s"),
    ("nan-setup", setter(dev("setup_s"), float("nan")), "setup_s"),
    ("bool-instances", setter(dev("instances"), True), "instances"),
    ("zero-instances", setter(dev("instances"), 0), "instances"),
    ("inf-timeout-factor", setter(lambda r: "orchestrator.timeout_factor", float("inf")), "timeout_factor"),
    ("inf-backoff", setter(lambda r: "orchestrator.retry.backoff_s", float("inf")), "backoff_s"),
    ("bool-budget", setter(lambda r: "campaign.budget", True), "campaign.budget"),
    ("string-budget", setter(lambda r: "campaign.budget", "lots"), "campaign.budget"),
    ("huge-lease", setter(lambda r: "bus.lease_ms", 10**15), "bus.lease_ms"),
    ("inf-speed", setter(lambda r: "clock", {"mode": "scaled", "speed": float("inf")}), "clock.speed"),
    ("tiny-mtbc", setter(dev("faults"), {"mtbc_h": 1e-9, "restart_s": 0}), "faults.mtbc_h"),
    ("inf-mtbc", setter(dev("faults"), {"mtbc_h": float("inf")}), "faults.mtbc_h"),
    ("fail-p-over-one", setter(dev("faults.fail_p"), 1.5), "faults.fail_p"),
    ("unknown-model", setter(lambda r: "chemistry.model", "alchemy"), "alchemy"),
    ("empty-box", empty_box, "chemistry.parameters"),
    ("inf-box", inf_box, "chemistry.parameters"),
    ("huge-box", huge_box, "chemistry.parameters"),
    ("negative-plus-param", negative_plus_param, "plus_param"),
    ("unknown-plus-param", unknown_plus_param, "plus_param"),
    ("target-nothing-produces", unknown_output_target, "nothing_makes_this"),
    ("min-over-max", min_over_max, "min"),
    ("duplicate-target", duplicate_target, "targets"),
    ("colliding-instance-names", colliding_instances, "devices"),
    ("type-with-slash", rename_first_device("spec/1"), "devices"),
    ("type-with-star", rename_first_device("spec*"), "devices"),
    ("type-with-hash", rename_first_device("spec#1"), "devices"),
    ("type-empty", rename_first_device(""), "devices"),
    ("name-traversal", setter(lambda r: "name", "../../etc/evil"), "name"),
    ("name-absolute", setter(lambda r: "name", "/tmp/evil"), "name"),
    ("name-400-chars", setter(lambda r: "name", "n" * 400), "name"),
    ("lab-with-slash", setter(lambda r: "lab", "a/b"), "lab"),
    ("planner-builtin", setter(lambda r: "campaign.planner", "builtins:dict"), "standard library"),
    ("planner-relative-import", setter(lambda r: "campaign.planner", ".agents:X"), "not of the form"),
    ("scheduler-stdlib-with-an-effect", setter(lambda r: "campaign.scheduler", "antigravity:X"), "standard library"),
    ("driver-main-module", setter(dev("driver"), "__main__:app"), "main module"),
    ("planner-unknown", setter(lambda r: "campaign.planner", "no-such-planner"), "no-such-planner"),
    ("scheduler-unknown", setter(lambda r: "campaign.scheduler", "no-such-rule"), "no-such-rule"),
    ("fallback-unknown", setter(lambda r: "campaign.fallback_scheduler", "nope"), "nope"),
    ("driver-unknown", setter(dev("driver"), "no-such-driver"), "no-such-driver"),
    ("driver-not-a-driver", setter(dev("driver"), "twin:Scenario"), "not a driver"),
    ("bad-listen", setter(lambda r: "bus.listen", ["not an endpoint"]), "bus.listen"),
    ("bad-connect-port", setter(lambda r: "bus.connect", ["tcp/127.0.0.1:99999"]), "bus.connect"),
    ("bad-zenoh-path", setter(lambda r: "bus.zenoh", {"no/such/path": 1}), "bus.zenoh"),
    ("unknown-field", setter(lambda r: "campaign.budgett", 5), "budgett"),
    ("workflow-unknown-device", setter(lambda r: "workflow", [{"step": "x", "device": "ghost"}]), "workflow"),
]


def generated_cases(tmp):
    cases = []
    for scen in SHIPPED:
        for cid, mutate, words in MUTATIONS:
            raw = shipped(scen)
            try:
                mutate(raw)
            except (KeyError, StopIteration, IndexError):
                continue  # the mutation does not apply to this scenario
            path = tmp / f"{scen}--{cid}.yaml"
            path.write_text(yaml.safe_dump(raw, allow_unicode=True))
            cases.append((path, words))
    return cases


def raw_cases(tmp):
    """Whole-file attacks: what no YAML dumper would write."""
    qd = (ROOT / "scenarios" / "quantum_dots.yaml").read_text()
    files = {
        "binary.yaml": (bytes(range(256)) * 4, "not UTF-8"),
        "utf16.yaml": (qd.encode("utf-16"), "UTF-16"),
        "empty.yaml": (b"", "mapping"),
        "a-list.yaml": (b"- 1\n- 2\n", "mapping"),
        "deep.yaml": (b"a: " + b"[" * 3000 + b"]" * 3000 + b"\n", "levels deep"),
        "deep-block.yaml": ("".join(f"{'  ' * i}k{i}:\n" for i in range(200)).encode(), "levels deep"),
        "bomb.yaml": (b'a: &a ["x","x","x","x","x","x","x","x","x"]\n' + b"".join(
            f'{chr(98 + i)}: &{chr(98 + i)} [*{chr(97 + i)},*{chr(97 + i)},*{chr(97 + i)},*{chr(97 + i)},'
            f'*{chr(97 + i)},*{chr(97 + i)},*{chr(97 + i)},*{chr(97 + i)},*{chr(97 + i)}]\n'.encode()
            for i in range(8)), "alias"),
        "duplicate-keys.yaml": (qd.replace("campaign:\n", "campaign:\n  budget: 3\n", 1).encode(), "twice"),
        "duplicate-device.yaml": (qd.replace("  spectrometer:\n", "  synthesiser:\n", 1).encode(), "twice"),
        "duplicate-on-a-line.yaml": (qd.replace("campaign:\n", "campaign: {budget: 3, budget: 4}\nx:\n", 1).encode(),
                                     "column"),  # one line's were let be: YAML kept the last
        "not-yaml.yaml": (b"name: [unclosed\n", "line"),
        "huge.yaml": (b"name: x\n" + b"# " + b"x" * (2 << 20) + b"\n", "KiB"),
        "tabs.yaml": (b"name:\n\t- x\n", "line"),
    }
    cases = []
    for fname, (data, words) in files.items():
        path = tmp / fname
        path.write_bytes(data)
        cases.append((path, words))
    (tmp / "a-directory.yaml").mkdir()
    cases.append((tmp / "a-directory.yaml", "directory"))
    cases.append((tmp / "missing.yaml", "not found"))
    return cases


def jobshop_cases(tmp):
    shop = {"name": "js", "lab": "js", "jobshop": {"file": "shop.txt"}}
    bodies = {"missing": None, "directory": "dir", "binary": bytes(range(256)), "zero": b"0 0\n",
              "negative": b"1 1\n0 -5\n", "short": b"2 2\n0 1 1 1\n", "not-numbers": b"two two\n",
              "bad-machine": b"1 1\n3 5\n", "huge-duration": b"1 1\n0 100000000000\n"}
    cases = []
    for cid, body in bodies.items():
        d = tmp / f"js-{cid}"
        d.mkdir()
        (d / "s.yaml").write_text(yaml.safe_dump(shop))
        if body == "dir":
            (d / "shop.txt").mkdir()
        elif body is not None:
            (d / "shop.txt").write_bytes(body)
        cases.append((d / "s.yaml", "shop.txt"))
    return cases


@pytest.fixture(scope="module")
def cases(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("hostile")
    return generated_cases(tmp) + raw_cases(tmp) + jobshop_cases(tmp)


class TimeLimit(Exception):
    pass


def _alarm(*_):
    raise TimeLimit()


def test_there_are_at_least_100_malformed_files(cases):
    assert len(cases) >= 100


def test_every_malformed_file_gets_a_clear_bounded_error_in_time(cases):
    problems = []
    previous = signal.signal(signal.SIGALRM, _alarm)
    try:
        for path, words in cases:
            signal.alarm(LIMIT_S)
            try:
                validate_file(path)
            except TimeLimit:
                problems.append(f"{path.name}: no answer within {LIMIT_S} s")
                continue
            except TwinError as exc:
                text = str(exc)
                if words.lower() not in text.lower():
                    problems.append(f"{path.name}: error does not mention {words!r}: {text[:300]}")
                elif str(path.name) not in text and "shop.txt" not in text:
                    problems.append(f"{path.name}: error does not name the file: {text[:300]}")
                elif len(text) > 4000:
                    problems.append(f"{path.name}: {len(text)} characters of error text")
            except BaseException as exc:  # noqa: BLE001 - anything else is the failure this test looks for
                problems.append(f"{path.name}: {type(exc).__name__}: {str(exc)[:200]}")
            else:
                problems.append(f"{path.name}: accepted")
            finally:
                signal.alarm(0)
    finally:
        signal.signal(signal.SIGALRM, previous)
    assert not problems, f"{len(problems)} of {len(cases)}:\n" + "\n".join(problems)


def test_the_shipped_scenarios_still_validate():
    for name in [*SHIPPED, "jobshop"]:
        validate_file(ROOT / "scenarios" / f"{name}.yaml")


def test_twin_validate_exits_2_with_no_traceback(cases):
    picked = [p for p, _ in cases if p.name in ("binary.yaml", "bomb.yaml", "deep.yaml", "a-directory.yaml")]
    picked.append(next(p for p, _ in cases if "inf-speed" in p.name))
    out = subprocess.run([sys.executable, "-m", "twin", "validate", *map(str, picked)], capture_output=True,
                         text=True, cwd=ROOT, timeout=120)
    assert out.returncode == 2
    assert "Traceback" not in out.stderr and out.stderr.count("✗") == len(picked)


def test_validating_a_scenario_runs_no_module_of_pythons_own_that_it_names(tmp_path):
    # importing `this` prints the Zen of Python; `antigravity` opens a web browser; `idlelib.idle` starts IDLE
    raw = shipped("quantum_dots")
    raw["campaign"]["scheduler"] = "this:X"
    path = tmp_path / "s.yaml"
    path.write_text(yaml.safe_dump(raw))
    out = subprocess.run([sys.executable, "-m", "twin", "validate", str(path)], capture_output=True, text=True,
                         cwd=ROOT, timeout=120)
    assert out.returncode == 2 and "'this' is Python's own standard library" in out.stderr
    assert "Zen of Python" not in out.stdout + out.stderr


def test_an_unsafe_name_is_explained_not_shown_as_a_regex(tmp_path):
    raw = shipped("quantum_dots")
    raw["devices"]["plate reader"] = raw["devices"].pop("spectrometer")
    path = tmp_path / "s.yaml"
    path.write_text(yaml.safe_dump(raw))
    with pytest.raises(TwinError) as info:
        validate_file(path)
    text = str(info.value)
    assert "devices.plate reader: 'plate reader' is not a valid name (key)" in text and "^[" not in text
    raw = shipped("quantum_dots")
    raw["name"] = "müller-lab"  # a letter, but not one a bus key or every file system takes: the words say so
    path.write_text(yaml.safe_dump(raw, allow_unicode=True))
    with pytest.raises(TwinError, match=r"name: 'müller-lab' is not a valid name \(value\): use ASCII letters"):
        validate_file(path)


def test_a_named_pipe_is_read_when_written_and_refused_when_nothing_writes(tmp_path, monkeypatch):
    """`twin validate FIFO` with no writer waited for ever; `<(cat lab.yaml)` is a pipe too, and must still work."""
    import os
    import threading

    from twin.scenario import files

    pipe = tmp_path / "lab.yaml"
    os.mkfifo(pipe)
    text = (ROOT / "scenarios" / "flaky_lab.yaml").read_bytes()

    def write():
        with open(pipe, "wb") as f:  # opens once the reader has; the text in two parts
            f.write(text[:100])
            f.flush()
            f.write(text[100:])

    writer = threading.Thread(target=write)
    writer.start()
    assert files.read_text(pipe) == text.decode()
    writer.join()
    monkeypatch.setattr(files, "PIPE_WAIT_S", 0.2)
    with pytest.raises(TwinError, match=r"lab\.yaml(?s:.*)is a named pipe that nothing wrote to within 0.2 s"):
        validate_file(pipe)
