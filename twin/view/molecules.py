"""Reactions drawn by RDKit as PNG, for the viewer's route panel (imported only when a route runs)."""

from __future__ import annotations

MAX_ROWS = 30


def route_png(reactions: tuple[str, ...], width: int = 720, row: int = 180) -> bytes | None:
    """A route's reactions (``reactants>>product`` SMILES, in the order they run), one row each, as a PNG;
    None without RDKit or if it cannot read one of them (a hostile journal, say)."""
    try:
        from rdkit import rdBase
        from rdkit.Chem import rdChemReactions
        from rdkit.Chem.Draw import rdMolDraw2D
    except ImportError:  # the viewer works without RDKit; it just draws no molecules
        return None
    rdBase.DisableLog("rdApp.*")
    rows = []
    for reaction in reactions[:MAX_ROWS]:
        try:
            rxn = rdChemReactions.ReactionFromSmarts(str(reaction)[:2000], useSmiles=True)
        except ValueError:
            return None
        if rxn is None or not rxn.GetNumProductTemplates():
            return None
        rows.append(rxn)
    if not rows:
        return None
    drawer = rdMolDraw2D.MolDraw2DCairo(width, row * len(rows), width, row)
    for i, rxn in enumerate(rows):
        drawer.SetOffset(0, i * row)
        drawer.DrawReaction(rxn)
    drawer.FinishDrawing()
    return drawer.GetDrawingText()
