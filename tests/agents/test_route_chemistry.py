"""Route chemistry (agents.routes): the shipped templates each make their own example forwards and propose its
reactants backwards, a backwards match the forward chemistry would not make is not proposed, the stock reads
by any spelling of a molecule, and a broken template or stock file is refused naming the file, entry and fault."""

import pytest

from agents.routes import stock as stock_file
from agents.routes import templates as template_file
from agents.routes.templates import TemplateError, check_example, canonical, forward, retro

SHIPPED = template_file.load()


def test_the_shipped_set_covers_forty_reaction_classes_with_sources():
    assert len({t.name for t in SHIPPED}) >= 40
    names = " ".join(t.name for t in SHIPPED).lower()
    for must in ("amide coupling", "esterification", "acetylation", "williamson", "snar", "suzuki",
                 "buchwald", "reductive amination", "boc protection", "boc deprotection", "cbz protection",
                 "cbz deprotection", "grignard", "wittig", "aldol", "nitro reduction"):
        assert must in names, must
    assert all(t.source and 0 <= t.yield_pct[0] <= t.yield_pct[1] <= 100 and t.hours[1] > 0 for t in SHIPPED)


@pytest.mark.parametrize("template", SHIPPED, ids=lambda t: t.name)
def test_each_template_makes_its_example_and_proposes_its_reactants(template):
    assert check_example(template) == []


def test_a_backwards_match_the_forward_reaction_would_not_make_is_not_proposed():
    fischer = next(t for t in SHIPPED if t.name == "Fischer esterification")
    aspirin = "CC(=O)Oc1ccccc1C(=O)O"  # an aryl ester: Fischer esterifies alcohols, not phenols
    assert retro(fischer, aspirin) == []
    acetylation = next(t for t in SHIPPED if t.name == "O-acetylation with acetic anhydride")
    assert retro(acetylation, aspirin) == [tuple(sorted(["CC(=O)OC(C)=O", "O=C(O)c1ccccc1O"]))]
    # every proposal of every template for a real drug goes forwards to the drug again
    lidocaine = canonical("CCN(CC)CC(=O)Nc1c(C)cccc1C")
    proposals = [(t, r) for t in SHIPPED for r in retro(t, lidocaine)]
    assert len(proposals) >= 5
    assert all(lidocaine in forward(t, r) for t, r in proposals)


def test_the_stock_finds_a_molecule_however_it_is_written():
    stock = stock_file.load()
    assert len(stock) >= 250
    assert "OC(=O)c1ccccc1O" in stock and "O=C(O)c1ccccc1O" in stock  # salicylic acid, two spellings
    assert stock.get("CC(=O)OC(C)=O").name == "acetic anhydride" and stock.get("CC(=O)OC(C)=O").eur_per_g > 0
    assert "CC(=O)Oc1ccccc1C(=O)O" not in stock  # aspirin itself must be made


@pytest.mark.parametrize("change,says", [
    (lambda t: t.replace("[{acyl}:1](=[O:2])[OH].[{amine}:3]", "[{acyle}:1](=[O:2])[OH].[{amine}:3]"),
     "templates[0] ('amide coupling (acid + amine)'): {acyle} is not one of the atom queries"),
    (lambda t: t.replace("source: roughley; brown\n    example: {reactants: ['CC(=O)O'",
                         "source: roughly\n    example: {reactants: ['CC(=O)O'"),
     "source 'roughly' must name keys of `sources:`"),
    (lambda t: t.replace(">>[C:1](=[O:2])[N:3]\"", ">>[C:1](=[O:2])[N:3\"", 1), "is not a reaction SMARTS RDKit reads"),
    (lambda t: t.replace("    yield_pct: [60, 95]\n", "", 1), "missing yield_pct"),
    (lambda t: t.replace("name: amide from acyl chloride", "name: amide coupling (acid + amine)"),
     "a second template named 'amide coupling (acid + amine)'"),
    (lambda t: t.replace("yield_pct: [60, 95]", "yield_pct: [95, 60]", 1), "yield_pct must be [low, high]"),
    # a primary amine's query narrowed to secondary ones: the file read, and the template never disconnected an
    # amide of a primary amine again, its own example included
    (lambda t: t.replace('amine: "N;H2,H1;', 'amine: "N;H1;', 1),
     "templates[0] ('amide coupling (acid + amine)'): its example does not hold: forwards, CC(=O)O.NCc1ccccc1 does "
     "not give CC(=O)NCc1ccccc1"),
    (lambda t: t.replace("example: {reactants: ['CC(=O)O', 'NCc1ccccc1']", "example: {reactants: ['CC(=O)O', 7]", 1),
     "example must be {reactants: [SMILES, ...], product: SMILES}"),
])
def test_a_broken_template_file_is_refused_naming_the_template_and_fault(change, says):
    text = template_file.TEMPLATES.read_text()
    broken = change(text)
    assert broken != text
    with pytest.raises(TemplateError) as err:
        template_file.parse(broken, "my_templates.yaml")
    assert str(err.value).startswith("my_templates.yaml") and says in str(err.value), str(err.value)


@pytest.mark.parametrize("text,says", [
    ("smiles,name,eur_per_g\nCCO,ethanol,0.02\nC1CC,broken,1\n", "my_stock.csv:3: 'C1CC' is not a SMILES"),
    ("smiles,name,eur_per_g\nCCO,ethanol,0.02\nOCC,ethanol again,1\n", "my_stock.csv:3: OCC is the same molecule as line 2"),
    ("smiles,name,eur_per_g\nCCO,ethanol,cheap\n", "my_stock.csv:2: eur_per_g 'cheap' must be a number"),
    ("name,smiles\nethanol,CCO\n", "my_stock.csv:1: the first row must be the header"),
])
def test_a_broken_stock_file_is_refused_naming_the_line(text, says):
    with pytest.raises(stock_file.StockError, match=None) as err:
        stock_file.parse(text, "my_stock.csv")
    assert says in str(err.value), str(err.value)


def test_a_stock_of_your_own_needs_only_smiles(tmp_path):
    mine = stock_file.parse("# my shelf\nsmiles\nCCO\nc1ccccc1N\n", "shelf.csv")
    assert len(mine) == 2 and "Nc1ccccc1" in mine and mine.get("CCO").eur_per_g is None
    excel = tmp_path / "shelf.csv"  # as a spreadsheet saves "CSV UTF-8": a byte-order mark first, CR LF
    excel.write_bytes(b"\xef\xbb\xbfsmiles,name,eur_per_g\r\nCCO,ethanol,0.02\r\nc1ccccc1N,aniline,\r\n")
    again = stock_file.load(excel)
    assert len(again) == 2 and again.get("CCO").eur_per_g == 0.02 and again.get("Nc1ccccc1").name == "aniline"


def test_an_aizynthfinder_style_template_table_is_searched_like_our_own(tmp_path):
    import gzip

    from agents.routes.plan import plan_breadth_first
    from agents.routes.templates import TemplateError, load

    rows = ["\t".join(["", "template_hash", "classification", "retro_template", "template_code"]),
            "\t".join(["0", "ab12", "1.2.1 Amide coupling",
                       "[C:1](=[O:2])-[NH;D2;+0:3]>>[C:1](=[O:2])-[OH].[NH2;D1;+0:3]", "17"])]
    table = tmp_path / "uspto_templates.csv.gz"
    table.write_bytes(gzip.compress("\n".join(rows).encode()))
    (only,) = load(table)
    assert only.name == "1.2.1 Amide coupling #17" and only.yield_pct == (50.0, 90.0)
    first = ["\t".join(row.split("\t")[i] for i in (3, 1, 2, 4)) for row in rows]  # retro_template first
    excel = tmp_path / "uspto_templates.tsv"  # as a spreadsheet saves it: a byte-order mark first, CR LF
    excel.write_bytes(b"\xef\xbb\xbf" + "\r\n".join(first).encode())
    assert [(t.name, t.smarts) for t in load(excel)] == [(only.name, only.smarts)]
    route = plan_breadth_first("CC(=O)Nc1ccc(O)cc1", templates=table)
    assert route["solved"] and route["steps"][0]["reaction"] == only.name
    assert sorted(route["steps"][0]["reactants"]) == sorted(["CC(=O)O", "Nc1ccc(O)cc1"])
    bad = tmp_path / "bad.csv"
    bad.write_text("smiles,name\nCCO,ethanol\n")
    with pytest.raises(TemplateError, match="no retro_template column"):
        load(bad)
