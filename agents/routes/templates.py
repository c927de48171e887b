"""Reaction templates: read from a YAML file, applied forwards (reactants → product) and backwards (a molecule →
the reactants that make it), with RDKit.

A template is written forwards (``agents/routes/data/templates.yaml`` says how); backwards it is the same
reaction with its sides swapped, and a disconnection is kept only if the forward reaction, run on the reactants
proposed, gives the molecule back — a retro match the forward chemistry would not make is never proposed.
"""

from __future__ import annotations

import itertools
import re
from dataclasses import dataclass, field
from functools import lru_cache
from pathlib import Path
from typing import Any

from rdkit import Chem, RDLogger
from rdkit.Chem import AllChem

from twin import ScenarioError, not_a_file, parse_yaml

RDLogger.DisableLog("rdApp.*")  # a failed sanitisation of a proposal is expected, and filtered, not news

DATA = Path(__file__).resolve().parent / "data"
TEMPLATES = DATA / "templates.yaml"
FIELDS = ("name", "class", "smarts", "yield_pct", "hours", "conditions", "source", "example")


class TemplateError(ValueError):
    """A template file that cannot be used; the message names the file, the template and what is wrong."""


@dataclass(frozen=True, eq=False)  # one object per template read: equal by identity, hashable
class Template:
    name: str
    reaction_class: str
    smarts: str
    yield_pct: tuple[float, float]
    hours: tuple[float, float]
    conditions: str
    source: str
    example: dict[str, Any]
    forward: Any = field(repr=False, compare=False)
    retro: Any = field(repr=False, compare=False)

    @property
    def arity(self) -> int:
        return self.forward.GetNumReactantTemplates()


#: The longest SMILES read: RDKit's parser crashes the process (a stack overflow, not an error) on a chain of some
#: 20,000 atoms, and a molecule a route is searched for is a few dozen atoms (aspirin's SMILES has 21 characters).
MAX_SMILES_CHARS = 2000


@lru_cache(maxsize=1 << 16)  # a search writes the same molecules again and again: each parse costs ~0.2 ms
def canonical(smiles: str) -> str | None:
    """RDKit's canonical SMILES of ``smiles`` (None if it does not parse, or is no molecule: RDKit reads '' as one of
    no atoms); a ValueError for one longer than ``MAX_SMILES_CHARS``."""
    if len(smiles) > MAX_SMILES_CHARS:
        raise ValueError(f"a SMILES of {len(smiles):,} characters ({smiles[:20]}...): the route search reads at most "
                         f"{MAX_SMILES_CHARS:,}, far more than a molecule it can make has")
    mol = Chem.MolFromSmiles(smiles)
    return Chem.MolToSmiles(mol) if mol is not None and mol.GetNumAtoms() else None


@lru_cache(maxsize=1 << 14)  # a molecule is parsed once for all 49 templates tried backwards on it; only read after
def _mol(smiles: str) -> Chem.Mol:
    mol = Chem.MolFromSmiles(smiles)
    if mol is None:
        raise ValueError(f"not a valid SMILES: {smiles!r}")
    return mol


def _products(reaction: Any, reactants: tuple[Chem.Mol, ...]) -> list[tuple[str, ...]]:
    """Every distinct outcome of ``reaction`` on ``reactants`` that sanitises, as canonical SMILES per product
    template (symmetric matches — three phenyls of an ylide — give the same outcome many times: each is
    written once, and only new ones are checked to read back)."""
    out, seen = [], set()
    for outcome in reaction.RunReactants(reactants):
        smiles = []
        for mol in outcome:
            try:
                Chem.SanitizeMol(mol)
            except (Chem.rdchem.MolSanitizeException, ValueError, RuntimeError):
                break
            smiles.append(Chem.MolToSmiles(mol))
        else:
            key = tuple(smiles)
            if key in seen:
                continue
            seen.add(key)
            again = tuple(canonical(s) for s in smiles)
            if None not in again and again not in out:
                out.append(again)
    return out


def forward(template: Template, reactants: tuple[str, ...]) -> set[str]:
    """The products ``template`` makes from ``reactants`` (in any order), canonical SMILES."""
    mols = [_mol(s) for s in reactants]
    made: set[str] = set()
    for order in itertools.permutations(mols, template.arity) if len(mols) >= template.arity else ():
        for outcome in _products(template.forward, tuple(order)):
            made.add(outcome[0])
    return made


def retro(template: Template, product: str) -> list[tuple[str, ...]]:
    """The sets of reactants (canonical SMILES, sorted) that ``template`` makes ``product`` from, each checked by
    running the template forwards on them."""
    target = canonical(product)
    if target is None:
        raise ValueError(f"not a valid SMILES: {product!r}")
    found: list[tuple[str, ...]] = []
    for outcome in _products(template.retro, (_mol(target),)):
        key = tuple(sorted(outcome))
        if key in found or target in outcome:
            continue
        if any(target == made[0] for made in _products(template.forward, tuple(_mol(s) for s in outcome))):
            found.append(key)
    return found


def _expand(smarts: str, atoms: dict[str, str], where: str) -> str:
    def one(match: re.Match) -> str:
        name = match.group(1)
        if name not in atoms:
            raise TemplateError(f"{where}: {{{name}}} is not one of the atom queries defined under `atoms:` "
                                f"({', '.join(sorted(atoms)) or 'none'})")
        return atoms[name]

    return re.sub(r"\{([A-Za-z_][A-Za-z0-9_]*)\}", one, smarts)


def _backwards(smarts: str, reaction: Any) -> str:
    """The reaction with its sides swapped, each mapped reactant atom reduced to its element (and aromaticity):
    run backwards, a query such as ``N;H2,H1`` would make RDKit give the atom that many hydrogens whatever its
    bonds (the forward check of every proposal applies the queries instead)."""
    plain = {}
    for mol in reaction.GetReactants():
        for a in mol.GetAtoms():
            if a.GetAtomMapNum():
                z, n = a.GetAtomicNum(), a.GetAtomMapNum()
                symbol = Chem.GetPeriodicTable().GetElementSymbol(z).lower() if a.GetIsAromatic() and z else f"#{z}"
                plain[n] = f"[{symbol}:{n}]" if z else f"[*:{n}]"
    reactants, product = smarts.split(">>")
    out, i = [], 0
    while i < len(reactants):  # bracket atoms, whose recursive queries ($(...)) hold brackets of their own
        if reactants[i] != "[":
            out.append(reactants[i])
            i += 1
            continue
        j, level = i, 0
        while True:
            level += {"[": 1, "]": -1}.get(reactants[j], 0)
            if level == 0:
                break
            j += 1
        mapped = re.search(r":(\d+)$", reactants[i + 1:j])
        out.append(plain[int(mapped.group(1))] if mapped else reactants[i:j + 1])
        i = j + 1
    return product + ">>" + "".join(out)


def _range(value: Any, where: str, what: str) -> tuple[float, float]:
    if (not isinstance(value, (list, tuple)) or len(value) != 2
            or not all(isinstance(x, (int, float)) for x in value) or not 0 <= value[0] <= value[1]):
        raise TemplateError(f"{where}: {what} must be [low, high] with 0 ≤ low ≤ high, got {value!r}")
    return float(value[0]), float(value[1])


def parse(text: str, source: str = "<templates>", check_examples: bool = True) -> list[Template]:
    """Templates from the YAML text of a template file (``source`` names it in errors), each checked against its
    own example unless ``check_examples`` is off (the shipped file's, which the tests check)."""
    try:  # within bounds: a file of a few hundred bytes whose aliases expand to 10^8 values is refused, not read
        doc = parse_yaml(text, source, "a template file in YAML (a large set loads as a CSV table)")
    except ScenarioError as exc:
        raise TemplateError(f"{source}: {'; '.join(exc.problems)}") from None
    if not isinstance(doc, dict) or not isinstance(doc.get("templates"), list):
        raise TemplateError(f"{source}: expected a mapping with a `templates:` list")
    sources = doc.get("sources") or {}
    if not isinstance(sources, dict):
        raise TemplateError(f"{source}: `sources:` must map keys to references")
    atoms = doc.get("atoms") or {}
    if not isinstance(atoms, dict) or not all(isinstance(v, str) for v in atoms.values()):
        raise TemplateError(f"{source}: `atoms:` must map names to SMARTS atom queries (text)")
    out, names = [], set()
    for i, raw in enumerate(doc["templates"]):
        where = f"{source}: templates[{i}]" + (f" ({raw.get('name')!r})" if isinstance(raw, dict) else "")
        if not isinstance(raw, dict):
            raise TemplateError(f"{where}: expected a mapping with {', '.join(FIELDS)}")
        missing = [f for f in FIELDS if f not in raw]
        if missing:
            raise TemplateError(f"{where}: missing {', '.join(missing)}")
        if raw["name"] in names:
            raise TemplateError(f"{where}: a second template named {raw['name']!r}; names must be unique")
        names.add(raw["name"])
        cited = [k.strip() for k in str(raw["source"]).split(";") if k.strip()]
        unknown = [k for k in cited if k not in sources]
        if unknown or not cited:
            raise TemplateError(f"{where}: source {raw['source']!r} must name keys of `sources:` "
                                f"({', '.join(sorted(sources)) or 'none defined'}), separated by ';'")
        smarts = _expand(str(raw["smarts"]), atoms, where)
        try:
            fwd = AllChem.ReactionFromSmarts(smarts)
            fwd.Initialize()
            back = AllChem.ReactionFromSmarts(_backwards(smarts, fwd))
            back.Initialize()
        except (ValueError, RuntimeError) as exc:
            raise TemplateError(f"{where}: smarts is not a reaction SMARTS RDKit reads ({exc})") from None
        if fwd.GetNumProductTemplates() != 1 or not 1 <= fwd.GetNumReactantTemplates() <= 3:
            raise TemplateError(f"{where}: smarts must make one product from one to three reactants "
                                f"(reactant.reactant>>product)")
        example = raw["example"]
        if (not isinstance(example, dict) or not isinstance(example.get("reactants"), list)
                or not example["reactants"] or not all(isinstance(r, str) for r in example["reactants"])
                or not isinstance(example.get("product"), str)):
            raise TemplateError(f"{where}: example must be {{reactants: [SMILES, ...], product: SMILES}}")
        template = Template(str(raw["name"]), str(raw["class"]), smarts, _range(raw["yield_pct"], where, "yield_pct"),
                            _range(raw["hours"], where, "hours"), str(raw["conditions"]),
                            "; ".join(sources[k] for k in cited), example, fwd, back)
        try:
            wrong = check_example(template) if check_examples else []
        except ValueError as exc:  # a SMILES too long to read
            raise TemplateError(f"{where}: example: {exc}") from None
        if wrong:  # the search would never use it where it was meant to be used
            raise TemplateError(f"{where}: its example does not hold: {wrong[0].partition(': ')[2]}; its smarts (or "
                                "an atom query it names) does not match the example's molecules as written: fix the "
                                "one that is wrong")
        out.append(template)
    return out


#: What an imported template (AiZynthFinder-style, no ranges given) is assumed to take and give.
IMPORTED_YIELD_PCT, IMPORTED_HOURS = (50.0, 90.0), (1.0, 12.0)


def parse_retro_table(text: str, source: str = "<templates>") -> list[Template]:
    """Templates from an AiZynthFinder-style table: a header, then a row per template with its retro SMARTS
    (``retro_template``: product>>reactants, mapped) and optionally ``classification``, ``template_code``,
    ``template_hash``; comma- or tab-separated (``.csv``, ``.csv.gz``). Run forwards as well (the sides swapped)
    for the search's round-trip check; yields and hours are ``IMPORTED_YIELD_PCT`` / ``IMPORTED_HOURS``."""
    import csv

    lines = text.splitlines()
    if not lines:
        raise TemplateError(f"{source}: empty; expected a header with a retro_template column, then a row each")
    dialect = "excel-tab" if lines[0].count("\t") > lines[0].count(",") else "excel"
    reader = csv.DictReader(lines, dialect=dialect)
    try:
        rows = list(reader)
    except csv.Error as exc:  # a field over csv's 128 KiB, an unclosed quote
        raise TemplateError(f"{source}: the table cannot be read past row {reader.line_num} ({exc})") from None
    if not rows or "retro_template" not in (rows[0].keys() if rows else ()):
        raise TemplateError(f"{source}: no retro_template column (header: {lines[0][:120]!r}); an AiZynthFinder "
                            "template table has one, with product>>reactants SMARTS")
    out, names = [], set()
    for i, row in enumerate(rows):
        where = f"{source}: row {i + 2}"
        retro_smarts = (row.get("retro_template") or "").strip()
        product, sep, reactants = retro_smarts.partition(">>")
        if not sep or not product or not reactants:
            raise TemplateError(f"{where}: retro_template {retro_smarts[:80]!r} is not product>>reactants SMARTS")
        if len(retro_smarts) > MAX_SMILES_CHARS:  # RDKit's parsers crash the process on some that long
            raise TemplateError(f"{where}: a retro_template of {len(retro_smarts):,} characters; a reaction's "
                                f"SMARTS is a few hundred, and at most {MAX_SMILES_CHARS:,} are read")
        try:
            back = AllChem.ReactionFromSmarts(retro_smarts)
            back.Initialize()
            fwd = AllChem.ReactionFromSmarts(reactants + ">>" + product)
            fwd.Initialize()
        except (ValueError, RuntimeError) as exc:
            raise TemplateError(f"{where}: retro_template is not a reaction SMARTS RDKit reads ({exc})") from None
        if back.GetNumReactantTemplates() != 1 or not 1 <= back.GetNumProductTemplates() <= 3:
            raise TemplateError(f"{where}: retro_template must take one product to one to three reactants")
        label = (row.get("classification") or "").strip() or "imported"
        name = f"{label} #{(row.get('template_code') or row.get('template_hash') or str(i)).strip()[:16]}"
        if name in names:
            name = f"{name} ({i})"
        names.add(name)
        out.append(Template(name, label[:64], reactants + ">>" + product, IMPORTED_YIELD_PCT, IMPORTED_HOURS, "",
                            source, {}, fwd, back))
    return out


#: The most a template file may hold, uncompressed (AiZynthFinder's USPTO table is under half of it).
MAX_TABLE_BYTES = 256 << 20


@lru_cache(maxsize=8)
def load(path: Path = TEMPLATES) -> tuple[Template, ...]:
    """The templates of a file (by default the shipped set), parsed once: this package's YAML, or an
    AiZynthFinder-style table (``.csv``, ``.tsv``, ``.csv.gz``)."""
    path = Path(path)
    if why := not_a_file(path):
        raise TemplateError(f"{path} {why}; give a template file (YAML, or a .csv/.tsv table)")
    try:
        if path.name.endswith(".gz"):
            import gzip

            with gzip.open(path) as f:  # read up to the bound, not decompressed whole: a gzip bomb is a few KB
                data = f.read(MAX_TABLE_BYTES + 1)
        else:
            with path.open("rb") as f:
                data = f.read(MAX_TABLE_BYTES + 1)
        if len(data) > MAX_TABLE_BYTES:
            raise TemplateError(f"{path}: more than {MAX_TABLE_BYTES >> 20} MiB of templates (uncompressed); a "
                                "route search here reads tables of up to some hundred thousand templates")
        text = data.decode("utf-8-sig")  # a byte-order mark first, as spreadsheets save CSV, is dropped
    except (OSError, EOFError) as exc:
        raise TemplateError(f"{path}: cannot read the template file ({getattr(exc, 'strerror', None) or exc})") from None
    except UnicodeDecodeError as exc:
        raise TemplateError(f"{path}: not UTF-8 text (byte {exc.start}): a template file is this package's YAML "
                            "or an AiZynthFinder-style CSV/TSV table, saved as UTF-8") from None
    if path.name.endswith((".csv", ".tsv", ".csv.gz", ".tsv.gz")):
        return tuple(parse_retro_table(text, str(path)))
    return tuple(parse(text, str(path), check_examples=path.resolve() != TEMPLATES.resolve()))


def check_example(template: Template) -> list[str]:
    """What is wrong with a template against its own example (empty: forwards it makes the product from the
    reactants, and backwards it proposes exactly those reactants)."""
    problems = []
    reactants = [canonical(s) for s in template.example["reactants"]]
    product = canonical(template.example["product"])
    if None in reactants or product is None:
        return [f"{template.name}: the example has a SMILES RDKit cannot read"]
    if product not in forward(template, tuple(reactants)):
        problems.append(f"{template.name}: forwards, {'.'.join(reactants)} does not give {product}")
    if tuple(sorted(reactants)) not in retro(template, product):
        problems.append(f"{template.name}: backwards, {product} does not give {'.'.join(sorted(reactants))} "
                        f"(gives {retro(template, product)})")
    return problems
