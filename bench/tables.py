"""What the benchmarks share: a markdown table on stdout (or JSON / CSV for machines), a free loopback port.

Every benchmark takes ``--json`` (its tables as one JSON document on stdout, instead of markdown) and
``--csv FILE`` (each table as CSV: the first to FILE, the k-th to FILE-k); both are taken out of ``sys.argv``
when this module is imported, before a benchmark parses its own options.
"""

from __future__ import annotations

import atexit
import csv
import json
import socket
import sys
from pathlib import Path


def _take(flag: str, with_value: bool = False) -> str | bool | None:
    if flag not in sys.argv:
        return None
    i = sys.argv.index(flag)
    if not with_value:
        del sys.argv[i]
        return True
    if i + 1 >= len(sys.argv):
        sys.exit(f"{flag} needs a file name")
    value = sys.argv[i + 1]
    del sys.argv[i:i + 2]
    return value


JSON = bool(_take("--json"))
CSV = _take("--csv", with_value=True)
_tables: list[dict] = []


def table(title: str, header: list[str], rows: list[list]) -> None:
    if CSV:
        path = Path(str(CSV))
        if _tables:
            path = path.with_name(f"{path.stem}-{len(_tables) + 1}{path.suffix}")
        with open(path, "w", newline="") as f:
            w = csv.writer(f)
            w.writerow(header)
            w.writerows(rows)
    _tables.append({"title": title, "columns": list(header), "rows": [dict(zip(header, r)) for r in rows]})
    if JSON:
        return
    widths = [max(len(str(x)) for x in col) for col in zip(header, *rows)]
    print(f"\n{title}")
    print("| " + " | ".join(h.ljust(w) for h, w in zip(header, widths)) + " |")
    print("|" + "|".join("-" * (w + 2) for w in widths) + "|")
    for r in rows:
        print("| " + " | ".join(str(x).ljust(w) for x, w in zip(r, widths)) + " |")


@atexit.register
def _print_json() -> None:
    if JSON:
        print(json.dumps({"tables": _tables}, default=str, indent=1))


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]
