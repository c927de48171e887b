"""Running a route's reactions: a reaction makes a crude product, purification trades mass for purity, an
LC-MS run finds the product's mass and its share of the sample.

A reaction's yield is drawn from its template's range and scaled by the purity of the intermediates it
takes; an intermediate (a sample made by an earlier reaction) decays while it waits, as exp(-age /
stability_s) of its product turns into a degradation product. A template the scenario marks as failing
(``chemistry.options.failing``, by template name or class) gives almost nothing: the product is not formed.
Masses are RDKit's: average molecular weight for milligrams, monoisotopic mass for the m/z LC-MS reports.
"""

from __future__ import annotations

import math
from functools import lru_cache
from typing import Any

import numpy as np

PROTON = 1.007276  # the [M+H]+ ion of positive electrospray
RECOVERY = (0.75, 0.92)  # share of the product a purification keeps
CARRY_OVER = (0.01, 0.04)  # share of each impurity it lets through
SIDE_PRODUCT = (0.03, 0.12)  # a side product's mass as a share of the product's
FAILED_YIELD = (0.0, 0.03)  # a reaction that does not work still leaves traces
DETECTION_MG = 0.05  # below this LC-MS sees no peak
#: What an LC-MS run reports (``target_*`` only on the route's last reaction, whose product is the target).
LCMS_OUTPUTS = frozenset({"mz_expected", "mz_found", "identity", "purity_pct", "product_mg", "yield_pct",
                          "impurities_mz", "made_at_s", "target_mg", "target_purity_pct"})


@lru_cache(maxsize=4096)
def weights(smiles: str) -> tuple[float, float]:
    """(average molecular weight g/mol, monoisotopic mass Da) of a molecule; ValueError if RDKit cannot read it."""
    from rdkit import Chem
    from rdkit.Chem import Descriptors

    mol = Chem.MolFromSmiles(smiles)
    if mol is None:
        raise ValueError(f"not a SMILES RDKit can read: {smiles!r}")
    return Descriptors.MolWt(mol), Descriptors.ExactMolWt(mol)


def aged(lot: dict[str, Any], now: float, stability_s: float) -> float:
    """The purity (0-1) of an intermediate lot now, after waiting since it was made."""
    purity = float(lot.get("purity", 1.0))
    age = max(0.0, now - float(lot.get("made_at_s", now)))
    return purity * (math.exp(-age / stability_s) if stability_s > 0 else 1.0)


def fails(params: dict[str, Any], failing: list[str]) -> bool:
    return bool({params.get("template"), params.get("class")} & set(failing))


def react(params: dict[str, Any], now: float, stability_s: float, failing: list[str],
          rng: np.random.Generator) -> dict[str, Any]:
    """The crude sample a reaction leaves: the product, unreacted limiting reagent, a side product."""
    reactants, product = _sides(params["reaction"])
    scale = float(params["scale_mmol"])
    lo, hi = params.get("yield_pct", (50, 90))
    y = rng.uniform(*FAILED_YIELD) if fails(params, failing) else rng.uniform(float(lo), float(hi)) / 100
    for lot in params.get("lots", []):  # impure or decayed intermediates give less
        y *= aged(lot, now, stability_s)
    mw_product = weights(product)[0]
    product_mg = scale * y * mw_product
    limiting = max(reactants, key=lambda r: weights(r)[0])
    impurities = {limiting: scale * (1 - y) * weights(limiting)[0]}
    impurities["side product"] = product_mg * rng.uniform(*SIDE_PRODUCT)
    return {"kind": "crude", "product": product, "product_mg": product_mg, "scale_mmol": scale,
            "impurities": impurities, "t_made": now}


def purify(sample: dict[str, Any], rng: np.random.Generator) -> dict[str, Any]:
    out = dict(sample, kind="purified")
    out["product_mg"] = sample["product_mg"] * rng.uniform(*RECOVERY)
    out["impurities"] = {k: mg * rng.uniform(*CARRY_OVER) for k, mg in sample["impurities"].items()}
    return out


def lcms(sample: dict[str, Any], params: dict[str, Any], now: float, stability_s: float, noise: float,
         rng: np.random.Generator) -> dict[str, Any]:
    """What an LC-MS run reports on a sample: the product's [M+H]+ m/z (found and expected), its share of the
    peak area, the milligrams that share stands for, the yield on the reaction's scale, and the age; for the
    route's last reaction (``params.final``) the same as ``target_mg`` and ``target_purity_pct``."""
    age = max(0.0, now - float(sample.get("t_made", now)))
    keep = math.exp(-age / stability_s) if stability_s > 0 else 1.0
    product_mg = sample["product_mg"] * keep
    impurities = dict(sample["impurities"])
    impurities["degradation product"] = sample["product_mg"] * (1 - keep)
    total = product_mg + sum(impurities.values())
    mw, exact = weights(sample["product"])
    expected = exact + PROTON
    seen = product_mg > DETECTION_MG
    purity = 100 * product_mg / total if total > 0 else 0.0
    purity = float(np.clip(purity * (1 + rng.normal(0, noise)), 0, 100)) if seen else 0.0
    mg = max(0.0, product_mg * (1 + rng.normal(0, noise))) if seen else 0.0
    out = {
        "mz_expected": round(expected, 4),
        "mz_found": round(expected + float(rng.normal(0, 0.002)), 4) if seen else 0.0,
        "identity": 1.0 if seen else 0.0,
        "purity_pct": round(purity, 2),
        "product_mg": round(mg, 2),
        "yield_pct": round(100 * (mg / mw) / sample["scale_mmol"], 2) if sample.get("scale_mmol") else 0.0,
        "impurities_mz": sorted(round(weights(k)[1] + PROTON, 4) for k, v in impurities.items()
                                if v > DETECTION_MG and not k.endswith("product")),
        "age_s": round(age, 1),
        "made_at_s": round(float(sample.get("t_made", now)), 1),
    }
    if params.get("final"):
        out["target_mg"], out["target_purity_pct"] = out["product_mg"], out["purity_pct"]
    return out


def _sides(reaction: str) -> tuple[list[str], str]:
    try:
        left, right = reaction.split(">>")
    except (AttributeError, ValueError):
        raise ValueError(f"'reaction' must be 'reactants>>product' SMILES, got {reaction!r}") from None
    reactants = [r for r in left.split(".") if r]
    if not reactants or not right:
        raise ValueError(f"'reaction' must be 'reactants>>product' SMILES, got {reaction!r}")
    for m in [*reactants, right]:
        weights(m)  # refuses what RDKit cannot read
    return reactants, right
