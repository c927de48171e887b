"""Scenario files: YAML validated by pydantic, one error per problem; ``twin schema`` exports the JSON Schema."""

from __future__ import annotations

import copy
import difflib
import os
from pathlib import Path
from typing import Any

from pydantic import ValidationError

from twin.core.errors import ScenarioError
from twin.scenario.beside import found_beside
from twin.scenario.files import MAX_DEPTH, read_yaml
from twin.scenario.model import Scenario
from twin.scenario.spec import Spec


def disagreeing(given: dict[str, Any], overrides: dict[str, Any]) -> list[str]:
    """The dotted fields a caller's own arguments (``given``: field -> value, None where not given) set otherwise
    than its ``overrides`` do: one of the two would win without a word."""
    return [field for field, value in given.items()
            if value is not None and field in overrides and overrides[field] != value]


def load(path: str | Path, overrides: dict[str, Any] | None = None, lab_only: bool = False) -> Scenario:
    """Read and validate a scenario file; ``ScenarioError`` lists every problem. ``lab_only``: a lab that takes
    its campaigns later (``twin lab serve``) may have no workflow."""
    path = Path(path)
    raw = read_yaml(path)
    if not isinstance(raw, dict):
        raise ScenarioError(str(path), ["the file must be a mapping with at least name, devices and workflow"
                                        + _if_a_shop(raw, path)])
    return _parsed(raw, _named_after_its_shop(raw, plain(overrides or {})), str(path), lab_only, path.parent)


def _if_a_shop(raw: Any, path: Path) -> str:
    """A job-shop instance given where a scenario goes: say how a scenario runs it."""
    words = str(raw).split() if isinstance(raw, (str, int)) else []
    if len(words) >= 4 and sum(w.isdigit() for w in words) >= 0.8 * len(words):
        return (f"; {path.name} looks like a job-shop instance: run it with `twin run scenarios/jobshop.yaml --set "
                f"jobshop.file={path.resolve()}`, or name it in a scenario as `jobshop: {{file: {path.name}}}`")
    return ""


def load_mapping(raw: dict[str, Any], overrides: dict[str, Any] | None = None, lab_only: bool = False) -> Scenario:
    """A scenario given as the mapping its file would hold (built in a notebook, say), validated as a file is;
    the files it names (a job shop, a security directory) are relative to the working directory. ``raw`` itself
    is left as it was."""
    source = f"the scenario {raw.get('name')!r} (a mapping)" if isinstance(raw.get("name"), str) else \
        "the scenario (a mapping)"
    raw = plain(raw)
    return _parsed(raw, _named_after_its_shop(raw, plain(overrides or {})), source, lab_only, Path.cwd())


def plain(value: Any, _within: tuple[int, ...] = ()) -> Any:
    """A copy of a value built in Python as its YAML would read: numpy's numbers and arrays (a budget of
    ``np.int64(20)``, a list of proposals from ``np.linspace``) as Python's, tuples as lists, paths as text."""
    if isinstance(value, (dict, list, tuple)):
        if id(value) in _within:
            raise ScenarioError("the scenario (a mapping)", ["it holds itself (a dict or list inside itself), which "
                                                              "no file can: give each part once"])
        if len(_within) > MAX_DEPTH:  # as a file is refused; thousands deep, a RecursionError
            raise ScenarioError("the scenario (a mapping)", [f"nested more than {MAX_DEPTH} levels deep; a scenario "
                                                              "or campaign does not need that"])
        within = (*_within, id(value))
        if isinstance(value, dict):
            return {key: plain(v, within) for key, v in value.items()}
        return [plain(v, within) for v in value]
    if isinstance(value, os.PathLike):
        return os.fspath(value)
    if type(value).__module__ == "numpy" and hasattr(value, "tolist"):
        return plain(value.tolist())
    return copy.deepcopy(value)


def _parsed(raw: dict[str, Any], overrides: dict[str, Any], source: str, lab_only: bool, base: Path) -> Scenario:
    """``raw`` with ``overrides``, validated, its files found from ``base``. A job shop's devices are read from its
    file, so what the scenario's ``devices`` says of them (``m0: {instances: 2}``: two of that machine), then
    overrides of them (``devices.m0.instances=2``), apply to the lab the shop makes."""
    shop = "jobshop" in raw or any(k.split(".")[0] == "jobshop" for k in overrides)
    later = {k: v for k, v in overrides.items() if shop and k.split(".")[0] == "devices"}
    if shop and isinstance(raw.get("devices"), dict):
        later = {**_leaves("devices", raw.pop("devices")), **later}
    scenario = _resolved(parse_overridden(raw, {k: v for k, v in overrides.items() if k not in later}, source,
                                          lab_only), base, source)
    if later:
        scenario = parse_overridden(scenario.model_dump(exclude_unset=True), later, source, lab_only)
    return found_beside(scenario, base)


def _leaves(prefix: str, tree: dict[str, Any]) -> dict[str, Any]:
    """A mapping as the dotted overrides that set each of its leaves: ``{m0: {instances: 2}}`` under ``devices``
    is ``devices.m0.instances=2``."""
    out: dict[str, Any] = {}
    for key, value in tree.items():
        if isinstance(value, dict) and value:
            out.update(_leaves(f"{prefix}.{key}", value))
        else:
            out[f"{prefix}.{key}"] = value
    return out


def _resolved(scenario: Scenario, base: Path, source: str) -> Scenario:
    """The files a scenario names, found relative to ``base``; a job shop read into devices and jobs."""
    if scenario.bus.security and not Path(scenario.bus.security).is_absolute():
        bus = scenario.bus.model_copy(update={"security": str((base / scenario.bus.security).resolve())})
        scenario = scenario.model_copy(update={"bus": bus})
    if scenario.jobshop is not None:
        from twin.scenario.jobshop import expand

        scenario = expand(scenario, base, source)
    return scenario


def _named_after_its_shop(raw: dict[str, Any], overrides: dict[str, Any]) -> dict[str, Any]:
    """A job-shop file given on the command line (``--set jobshop.file=jobshop/la02.txt``), or an instance of a
    collection (``--set jobshop.instance=ft10``), names the run after it (``jobshop_la02``: its summary and
    journal), unless the command line names it too."""
    file, instance = overrides.get("jobshop.file"), overrides.get("jobshop.instance")
    shop = instance if isinstance(instance, str) else Path(file).stem if isinstance(file, str) else None
    if shop is None or "name" in overrides:
        return overrides
    from twin.scenario.jobshop import run_name

    lab = raw.get("lab") if isinstance(raw.get("lab"), str) else "jobshop"
    return {**overrides, "name": run_name(lab, shop)}


def parse_overridden(raw: dict[str, Any], overrides: dict[str, Any], source: str, lab_only: bool = False) -> Scenario:
    """``raw`` with the command line's dotted ``overrides`` set, validated; an override through a name the
    scenario nearly has (``devices.spectrometr.instances``) adds "did you mean" to the problems it makes."""
    hints = [hint for dotted in overrides if (hint := _misspelt(raw, dotted))]
    spread = _to_each_campaign(raw, overrides)
    for dotted, value in {**spread, **overrides}.items():
        set_dotted(raw, dotted, value)
    try:
        return parse(raw, source, lab_only)
    except ScenarioError as exc:
        # a value spread to every campaign: its problem said once, as the lab's field's
        echoes = tuple(f"{k}:" for k in spread)
        own = {p.partition(":")[2] for p in exc.problems if not p.startswith(echoes)}
        problems = [p for p in exc.problems if not (p.startswith(echoes) and p.partition(":")[2] in own)]
        if not hints:
            raise ScenarioError(exc.source, problems) from None
        # the cause first; what a likely misspelt name lacks as a new entry (devices.spectromter.driver:
        # missing) only echoes it (a name near none may be a new entry: what it needs is said)
        made = tuple(hint.split(":", 1)[0] + end for hint in hints if "did you mean" in hint for end in ".:")
        raise ScenarioError(exc.source, [*hints, *(p for p in problems if not p.startswith(made))]) from None


def _to_each_campaign(raw: dict[str, Any], overrides: dict[str, Any]) -> dict[str, Any]:
    """In a lab of several campaigns, an override of the lab's ``campaign.FIELD`` (``--scheduler``, ``--set
    campaign.max_in_flight=2``, ``twin whatif --planners``) also set in each campaign that has a ``campaign:`` of
    its own, which replaces the lab's: it was silently ignored there. Not the seed: each campaign's is the lab's
    plus its place. An override of one campaign's field (``campaigns.1.campaign.scheduler``) still wins."""
    campaigns = raw.get("campaigns")
    if not isinstance(campaigns, list):
        return {}
    out = {}
    for dotted, value in overrides.items():
        if not dotted.startswith("campaign.") or dotted == "campaign.seed":
            continue
        for i, c in enumerate(campaigns):
            if isinstance(c, dict) and isinstance(c.get("campaign"), dict):
                out[f"campaigns.{i}.{dotted}"] = value
    return out


def _misspelt(raw: dict[str, Any], dotted: str) -> str | None:
    node: Any = raw
    model: Any = Scenario  # the section's model, while the path follows named fields and mappings' keys
    keyed: Any = None  # the model of a mapping's values (devices.<type>), when the next part is one of its keys
    parts = dotted.split(".")
    for i, p in enumerate(parts[:-1]):
        fields = getattr(model, "model_fields", {})
        if keyed is not None:
            model, keyed = keyed, None
        elif p in fields:
            annotation = fields[p].annotation
            model, keyed = (None, model_of(annotation)) if getattr(annotation, "__origin__", None) is dict else \
                (model_of(annotation), None)
        else:
            model = None
        if isinstance(node, list) and p.isdigit() and int(p) < len(node):
            node = node[int(p)]
        elif not isinstance(node, dict):
            return None
        elif p in node:
            node = node[p]
        elif p in fields:  # a section the file leaves to its defaults (bus, orchestrator.retry): not a misspelling
            return None
        else:
            names = [str(k) for k in node]
            close = difflib.get_close_matches(p, names, n=1)
            where = ".".join(parts[:i + 1])
            if close:
                return f"{where}: not in the scenario; did you mean {'.'.join([*parts[:i], close[0]])}?"
            return f"{where}: not in the scenario; {'.'.join(parts[:i]) or 'its top level'} has " + \
                (", ".join(names[:12]) + (", …" if len(names) > 12 else "") if names else "nothing")
    return None


def _known_near(loc: tuple, model: Any) -> str:
    """'; did you mean campaign.budget?' for a misspelt field of ``model``'s, or for one of a section where it
    does not belong (``targets`` at the top: chemistry.targets), or the fields its section has."""
    root_model = model
    for p in loc[:-1]:
        if model is None or isinstance(p, int):
            continue  # a list's item: the same model
        field = getattr(model, "model_fields", {}).get(p)
        if field is None:  # a mapping's key (devices.<type>): its values' model was taken already
            continue
        annotation = field.annotation
        for arg in (annotation, *getattr(annotation, "__args__", ())):
            if getattr(arg, "__origin__", None) in (dict, list):
                annotation = arg.__args__[-1]
        model = model_of(annotation)
    names = sorted(getattr(model, "model_fields", {}))
    if not names:
        return ""
    where = ".".join(str(p) for p in loc[:-1])
    close = difflib.get_close_matches(str(loc[-1]), names, n=1)
    if close:
        return f"; did you mean {where + '.' if where else ''}{close[0]}?"
    elsewhere = _fields_named(str(loc[-1]), root_model)
    if elsewhere:
        nearest = [p for p in elsewhere if p.count(".") == min(q.count(".") for q in elsewhere)]
        return f"; did you mean {' or '.join(nearest[:3])}?"
    return f"; {where or 'the top level'} has {', '.join(names[:16])}{', …' if len(names) > 16 else ''}"


def _fields_named(name: str, model: Any, prefix: str = "", depth: int = 3) -> list[str]:
    """The dotted paths of the fields called ``name`` in ``model``'s sections (``targets`` ->
    ``chemistry.targets``); a mapping's or list's values are written ``<name>`` or ``<n>``."""
    found: list[str] = []
    for field_name, field in getattr(model, "model_fields", {}).items():
        path = f"{prefix}{field_name}"
        if field_name == name:
            found.append(path)
        if depth <= 1:
            continue
        annotation, inner = field.annotation, ""
        for arg in (annotation, *getattr(annotation, "__args__", ())):
            origin = getattr(arg, "__origin__", None)
            if origin in (dict, list):
                annotation, inner = arg.__args__[-1], ".<name>" if origin is dict else ".<n>"
        sub = model_of(annotation)
        if sub is not None and sub is not model:
            found += _fields_named(name, sub, f"{path}{inner}.", depth - 1)
    return found


def model_of(annotation: Any) -> Any:
    """The pydantic model a field holds (``Bus``, or ``Training | None``'s), if any."""
    for arg in (annotation, *getattr(annotation, "__args__", ())):
        if hasattr(arg, "model_fields"):
            return arg
    return None


def parse(raw: dict[str, Any], source: str = "<scenario>", lab_only: bool = False) -> Scenario:
    try:
        return Scenario.model_validate(raw, context={"lab_only": lab_only})
    except ValidationError as exc:
        raise ScenarioError(source, problems_of(exc, raw)) from None


def problems_of(exc: ValidationError, raw: Any, root: Any = None) -> list[str]:
    """One line per problem, each naming its field; ``root``: the model validated (a scenario by default)."""
    errors: list[dict[str, Any]] = [{**e, "loc": _untagged(e, raw)} for e in exc.errors()]
    inside = [e["loc"] for e in errors]
    errors = [e for e in errors if not (isinstance(e.get("input"), dict) and e["type"].endswith(("_type", "_parsing"))
                                        and any(loc[:len(e["loc"])] == e["loc"] != loc for loc in inside))]
    return [line for e in errors for line in describe(e, raw, root).split("\n")]


def _untagged(err: Any, raw: Any) -> tuple[Any, ...]:
    """``err``'s location without the names pydantic gives the members of a union (``used_by.measure.Usage.fixed``,
    ``used_by.measure.float``): a part that is no key or index of the file where it stands (but the field a
    ``missing`` error names). A mapping where a number or a section goes then keeps only its section's problems."""
    loc, node, kept = err["loc"], raw, []
    for i, part in enumerate(loc):
        here = isinstance(node, dict) and part in node or isinstance(node, list) and isinstance(part, int) \
            and -len(node) <= part < len(node)
        if here:
            node = node[part]
        elif part != "[key]" and not (err["type"] == "missing" and i == len(loc) - 1):
            continue
        kept.append(part)
    return tuple(kept)


def describe(err: Any, raw: dict[str, Any], root: Any = None) -> str:
    loc = ".".join(str(p) for p in err["loc"])
    if err["type"] == "extra_forbidden":
        return f"{loc}: unknown field{_known_near(err['loc'], root or Scenario)} (`twin schema` lists the fields)"
    if err["type"] == "missing":
        return f"{loc}: required field is missing"
    if err["type"] == "string_pattern_mismatch":
        where = loc.removesuffix(".[key]")
        what = "key" if loc.endswith("[key]") else "value"
        allowed = ("ASCII letters, digits, '_' or '-', at most 64" if where == "lab" else
                   "ASCII letters, digits, '_', '-' or '.', at most 63, starting with a letter, digit or '_'")
        return (f"{where}: {str(err.get('input'))[:80]!r} is not a valid name ({what}): use {allowed} (names "
                "become bus keys and file names)")
    value = err.get("input")
    text = repr(value)
    shown = f" (got {text if len(text) <= 80 else text[:79] + '…'})"
    if isinstance(value, dict):  # a section's own problems name its fields; a mapping where a value goes, its keys
        keys = ", ".join(map(str, value))[:80]
        shown = "" if not err["type"].endswith(("_type", "_parsing")) else f" (got a mapping of {keys})" if value \
            else " (got an empty mapping, {})"
    msg = err["msg"].removeprefix("Value error, ")
    if err["type"] == "model_type":  # pydantic says "a valid dictionary or instance of JobShop"
        msg = f"should be a mapping{_of_fields(str(err.get('ctx', {}).get('class_name', '')))}"
    if not loc:  # the scenario's own checks across fields: each line names its field
        return msg
    if err["type"] == "int_type" and isinstance(value, float) and value.is_integer() and abs(value) < 1e18:
        shown += f": write it as a whole number, {int(value)}"  # 1e2 or 100.0 where a count goes
    if err["type"] == "list_type" and isinstance(value, (str, int, float)):  # `--set bus.listen=tcp/…:7447`
        shown += f": write a list, [{value}] (quoted on a command line: --set '{loc}=[{value}]')"
    return f"{loc}: {msg}{shown}"


def _of_fields(class_name: str) -> str:
    """`` of its fields: file`` for a section's class (its required fields first), or "" for a class not found."""
    found = [c for c in _specs(Spec) if c.__name__ == class_name]
    if not found:
        return ""
    fields = found[0].model_fields
    names = sorted(fields, key=lambda n: not fields[n].is_required())
    return f" of its fields: {', '.join(names)} (`twin schema` says what each means)"


def _specs(cls: type[Spec]) -> list[type[Spec]]:
    subs: list[type[Spec]] = cls.__subclasses__()
    return [c for sub in subs for c in (sub, *_specs(sub))]


def set_dotted(raw: dict[str, Any], dotted: str, value: Any) -> None:
    """Set ``raw["a"]["b"]["c"] = value`` for ``dotted = "a.b.c"``, creating the mappings that are missing; a
    number indexes a list (``orchestrator.recovery.0.timeout_s``). A path through something that is neither is a
    ScenarioError that names it."""
    node: Any = raw
    *parents, leaf = dotted.split(".")
    for i, p in enumerate([*parents, leaf]):
        last = i == len(parents)
        if isinstance(node, list):
            if not p.isdigit() or int(p) >= len(node):
                raise ScenarioError(dotted, [f"{'.'.join(parents[:i]) or '(top)'}: a list of {len(node)}: "
                                             f"{p!r} is not an index of it (0-{len(node) - 1})"])
            if last:
                node[int(p)] = value
            else:
                node = node[int(p)]
        elif isinstance(node, dict):
            if last:
                node[p] = value
            else:
                node = node.setdefault(p, {})
        else:
            raise ScenarioError(dotted, [f"{'.'.join(parents[:i])}: {str(node)[:60]!r} has no field {p!r}"])


def json_schema() -> dict[str, Any]:
    return Scenario.model_json_schema()
