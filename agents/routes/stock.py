"""The stock: building blocks a route may buy, read from a CSV file (``smiles,name,eur_per_g``; lines starting
with ``#`` are comments), looked up by RDKit's canonical SMILES."""

from __future__ import annotations

import csv
from dataclasses import dataclass
from functools import lru_cache
from pathlib import Path

from agents.routes.templates import DATA, canonical
from twin import not_a_file

STOCK = DATA / "stock.csv"


class StockError(ValueError):
    """A stock file that cannot be used; the message names the file, the line and what is wrong."""


@dataclass(frozen=True)
class Item:
    smiles: str  # canonical
    name: str
    eur_per_g: float | None


class Stock:
    def __init__(self, items: dict[str, Item], source: str) -> None:
        self.items, self.source = items, source

    def __contains__(self, smiles: str) -> bool:
        return smiles in self.items or canonical(smiles) in self.items

    def __len__(self) -> int:
        return len(self.items)

    def get(self, smiles: str) -> Item | None:
        return self.items.get(smiles) or self.items.get(canonical(smiles) or "")


def parse(text: str, source: str = "<stock>") -> Stock:
    lines = [(n, line) for n, line in enumerate(text.splitlines(), 1) if line.strip() and not line.lstrip().startswith("#")]
    if not lines:
        raise StockError(f"{source}: no building blocks (expected a header smiles,name,eur_per_g and a row each)")
    rows = list(csv.reader(line for _, line in lines))
    header = [h.strip() for h in rows[0]]
    if header[:1] != ["smiles"]:
        raise StockError(f"{source}:{lines[0][0]}: the first row must be the header smiles,name,eur_per_g "
                         f"(name and eur_per_g optional), got {','.join(header)}")
    items: dict[str, Item] = {}
    where_of: dict[str, int] = {}
    for (n, _), row in zip(lines[1:], rows[1:]):
        record = dict(zip(header, (c.strip() for c in row)))
        try:
            smiles = canonical(record.get("smiles", ""))
        except ValueError as exc:
            raise StockError(f"{source}:{n}: {exc}") from None
        if smiles is None:
            raise StockError(f"{source}:{n}: {record.get('smiles')!r} is not a SMILES RDKit can read")
        if smiles in items:
            raise StockError(f"{source}:{n}: {record['smiles']} is the same molecule as line {where_of[smiles]}; "
                             f"list each building block once")
        price = record.get("eur_per_g") or None
        try:
            value = float(price) if price is not None else None
        except ValueError:
            value = -1.0
        if value is not None and not value >= 0:
            raise StockError(f"{source}:{n}: eur_per_g {price!r} must be a number ≥ 0 (or empty: unknown)")
        items[smiles] = Item(smiles, record.get("name") or smiles, value)
        where_of[smiles] = n
    return Stock(items, source)


#: The largest stock file read: each building block is parsed by RDKit (~0.2 ms), so a million take minutes.
MAX_STOCK_BYTES = 64 << 20


@lru_cache(maxsize=8)
def load(path: Path = STOCK) -> Stock:
    if why := not_a_file(path):
        raise StockError(f"{path} {why}; a stock file is CSV: smiles[,name,eur_per_g]")
    try:
        with Path(path).open("rb") as f:
            data = f.read(MAX_STOCK_BYTES + 1)
        if len(data) > MAX_STOCK_BYTES:
            raise StockError(f"{path}: more than {MAX_STOCK_BYTES >> 20} MiB; a stock file here lists up to some "
                             "hundred thousand building blocks (each is parsed with RDKit as the file is read)")
        text = data.decode("utf-8-sig")  # a spreadsheet's "CSV UTF-8" starts with a byte-order mark
    except OSError as exc:
        raise StockError(f"{path}: cannot read the stock file ({exc.strerror})") from None
    except UnicodeDecodeError as exc:
        raise StockError(f"{path}: not a text file (byte {exc.start} is not UTF-8); a stock file is CSV: "
                         "smiles[,name,eur_per_g]") from None
    return parse(text, str(path))
