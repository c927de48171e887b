"""Find devices, planners and schedulers by entry point or by 'package.module:Class'."""

from __future__ import annotations

import ast
import difflib

import functools
import importlib
import importlib.util
import inspect
import sys
from pathlib import Path
from importlib.metadata import EntryPoint, entry_points
from typing import Any

from twin.core.errors import DriverError, PluginError

GROUPS = {"devices": "labtwin.devices", "planners": "labtwin.planners", "schedulers": "labtwin.schedulers",
          "trainers": "labtwin.trainers", "routes": "labtwin.routes", "route_targets": "labtwin.route_targets"}
#: What a plugin of each kind must have, and where its protocol is written.
_NAMES = {"devices": "driver", "routes": "route planner", "route_targets": "route target set"}  # in errors
_DOCS = {"devices": "docs/drivers.md", "routes": "docs/routes.md", "route_targets": "docs/routes.md"}
PROTOCOLS = {"devices": ("run", "safe_state"), "planners": ("propose",), "schedulers": ("decide",)}
#: Plugins the lab calls for an answer there and then (a plain ``def``): what it does instead of awaiting one.
_ANSWERS_AT_ONCE = {
    "schedulers": "a scheduler's answer at once: make it a plain `def`; a scheduler that must wait on something "
                  "elsewhere (a service, another process) is an agent on the bus (campaign.scheduler: remote, "
                  "docs/wire.md)",
    "planners": "a planner's answer at once: make it a plain `def` (on a scaled or wall clock the lab asks it in a "
                "worker thread, so a slow fit or a blocking call there stalls nothing)"}
#: The logger of what a plugin warns of when it is made for a lab (a policy trained on other labs). A command makes
#: each plugin once to check it before its runs, and the warning is given then; a bench's or a what-if's workers,
#: which make the plugin again for every run, keep it quiet rather than repeat it.
CHECKS_LOGGER = "twin.plugin_checks"


@functools.cache
def installed(kind: str) -> dict[str, EntryPoint]:
    """The installed plugins of a kind, looked up once per process (a look-up costs ~1.7 ms)."""
    return {ep.name: ep for ep in entry_points(group=GROUPS[kind])}


def with_policy(kind: str, spec: str) -> tuple[str, dict[str, Any]]:
    """``"rl:policies/x.zip"`` → ``("rl", {"policy": "policies/x.zip"})`` when ``rl`` is installed;
    anything else (a name, a ``package.module:Class`` string) is returned unchanged."""
    name, sep, rest = spec.partition(":")
    if sep and rest and name in installed(kind):
        return name, {"policy": rest}
    return spec, {}


def load(kind: str, name: str) -> Any:
    """The class ``name`` refers to, checked against its kind's protocol; a precise error says what is
    installed instead."""
    obj = _load(kind, name)
    missing = [m for m in PROTOCOLS.get(kind, ()) if not callable(getattr(obj, m, None))]
    if missing or not callable(obj):
        error = DriverError if kind == "devices" else PluginError
        what = kind[:-1] if kind != "devices" else "driver"
        raise error(f"{name!r} is {_what_it_is(obj)}, not a {what}: a {what} is a class with "
                    f"{', '.join(m + '()' for m in PROTOCOLS.get(kind, ()))} (see {_DOCS.get(kind, 'docs/plugins.md')})")
    if kind == "devices":
        plain = [m for m in PROTOCOLS["devices"] if not inspect.iscoroutinefunction(getattr(obj, m))]
        if plain:
            raise DriverError(f"{name!r}: {' and '.join(m + '()' for m in plain)} must be `async def`: the lab "
                              f"awaits {'it' if len(plain) == 1 else 'them'} (see docs/drivers.md)")
    elif kind in _ANSWERS_AT_ONCE and inspect.iscoroutinefunction(getattr(obj, PROTOCOLS[kind][0])):
        raise PluginError(f"{name!r}: {PROTOCOLS[kind][0]}() is `async def`, and the lab takes {_ANSWERS_AT_ONCE[kind]}"
                          " (see docs/plugins.md)")
    return obj


def parameters_unimported(kind: str, name: str) -> tuple[list[str], bool] | None:
    """An installed plugin's constructor, read from its source without importing it (a planner's module may import
    scikit-learn, torch or RDKit: seconds): the names it takes by keyword, and whether it takes any keyword (a
    ``**kwargs`` not named ``_``). None where the source does not say plainly (a class with bases, a metaclass, a
    ``__new__`` or no ``__init__`` of its own, a decorated one, a name bound again or imported from elsewhere, no
    source): load it to know."""
    ep = installed(kind).get(name)
    module, _, attr = (ep.value.partition(":") if ep is not None else ("", "", ""))
    module, attr = module.strip(), attr.strip()
    if not attr.isidentifier():
        return None
    try:
        spec = importlib.util.find_spec(module)
        if spec is None or not spec.origin or not spec.origin.endswith(".py"):
            return None
        body = ast.parse(Path(spec.origin).read_bytes()).body
    except (ImportError, ValueError, OSError, SyntaxError):
        return None
    defined = [n for n in body if isinstance(n, (ast.ClassDef, ast.FunctionDef)) and n.name == attr]
    bound = [n for n in body if isinstance(n, (ast.Assign, ast.AnnAssign, ast.AugAssign)) and attr in _targets(n)]
    if len(defined) != 1 or bound or defined[0].decorator_list:
        return None
    found = defined[0]
    if isinstance(found, ast.ClassDef):
        own = {n.name for n in found.body if isinstance(n, (ast.FunctionDef, ast.AsyncFunctionDef))}
        own |= {t for n in found.body if isinstance(n, (ast.Assign, ast.AnnAssign)) for t in _targets(n)}
        inits = [n for n in found.body if isinstance(n, ast.FunctionDef) and n.name == "__init__"]
        if len(inits) != 1 or inits[0].decorator_list or found.bases or found.keywords or own & {"__new__",
                                                                                                  "__signature__"}:
            return None
        args = inits[0].args
        positional = [*args.posonlyargs, *args.args][1:]  # without self
    else:
        args = found.args
        positional = [*args.posonlyargs, *args.args]
    named = [a.arg for a in (*positional, *args.kwonlyargs) if a not in args.posonlyargs]
    return named, args.kwarg is not None and args.kwarg.arg != "_"


def _targets(node: ast.Assign | ast.AnnAssign | ast.AugAssign) -> set[str]:
    return {t.id for t in (node.targets if isinstance(node, ast.Assign) else [node.target])
            if isinstance(t, ast.Name)}


def _what_it_is(obj: Any) -> str:
    kind = "class" if isinstance(obj, type) else type(obj).__name__
    return f"the {kind} {getattr(obj, '__qualname__', repr(obj))[:60]}"


def _load(kind: str, name: str) -> Any:
    error = DriverError if kind == "devices" else PluginError
    if ":" in name:
        return _import_string(name, error)
    eps = installed(kind)
    if name not in eps:
        have = ", ".join(sorted(eps)) or "none"
        near = difflib.get_close_matches(name, list(eps), n=1)
        raise error(
            f"unknown {_NAMES.get(kind, kind[:-1])} {name!r}{f' (did you mean {near[0]!r}?)' if near else ''}. "
            f"Installed: {have}. "
            f"Use one of those, or a 'package.module:{'function' if kind in ('routes', 'route_targets') else 'Class'}' string"
            + ("; `twin devices` lists drivers." if kind == "devices" else ".")
        )
    try:
        return eps[name].load()
    except Exception as exc:
        raise error(f"{_NAMES.get(kind, kind[:-1])} {name!r} ({eps[name].value}) failed to load: {exc}") from exc


def _where_modules_come_from(exc: ImportError) -> str:
    """What to do when a class string's module is not found: labtwin imports only what Python can (never a file
    because it lies beside a scenario, which may come from anyone)."""
    missing = getattr(exc, "name", None) or ""
    here = [f for f in (Path.cwd() / f"{missing}.py", Path.cwd() / missing / "__init__.py") if missing and f.exists()]
    if here:
        return (f"{here[0].relative_to(Path.cwd())} is in this folder, but a scenario's code is imported only from "
                f"installed packages or PYTHONPATH: run with PYTHONPATH=. (or `pip install -e` its package; "
                "`twin driver new` writes one)")
    return ("Is its package installed? (`pip install -e` it; `twin driver new` writes one.) A module of your own "
            "not in a package: put its folder on PYTHONPATH")


def _import_string(spec: str, error: type[Exception]) -> Any:
    module_name, _, attr = spec.partition(":")
    if not all(p.isidentifier() for p in (*module_name.split("."), *attr.split("."))):
        raise error(f"{spec!r} is not of the form 'package.module:Class'")
    top = module_name.partition(".")[0]
    if top in sys.stdlib_module_names or top == "__main__":
        # no plugin lives there, and a scenario (which may come from anyone) must not run this, antigravity or idlelib
        # by naming them: importing some of them does something
        own = "standard library" if top != "__main__" else "main module"
        raise error(f"{spec!r}: {top!r} is Python's own {own}, which holds no labtwin plugin; name a class of an "
                    "installed package (`twin driver new` writes one)")
    try:
        module = importlib.import_module(module_name)
    except ImportError as exc:
        raise error(f"could not import {module_name!r} for {spec!r}: {exc}. {_where_modules_come_from(exc)}") from exc
    obj = module
    for part in attr.split("."):
        try:
            obj = getattr(obj, part)
        except AttributeError:
            classes = [name for name, value in vars(module).items() if inspect.isclass(value)
                       and value.__module__ == module.__name__] if part == attr else []
            near = difflib.get_close_matches(part, classes, n=1)
            hint = f" (did you mean {module_name}:{near[0]}?)" if near else \
                f"; its classes: {', '.join(sorted(classes)[:10])}" if classes else ""
            raise error(f"module {module_name!r} has no attribute {attr!r} (from {spec!r}){hint}") from None
    return obj
