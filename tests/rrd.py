"""Read a Rerun recording back into plain Python, for assertions."""

from __future__ import annotations

import subprocess
import sys
from collections import defaultdict
from pathlib import Path

import pyarrow as pa
from rerun.chunk import RrdReader


def _plain(v):
    if isinstance(v, list):
        return [_plain(x) for x in v]
    return v


def _column(col: pa.Array) -> list:
    if pa.types.is_duration(col.type):
        return [None if v is None else v / 1e9 for v in col.cast(pa.int64()).to_pylist()]
    return col.to_pylist()


def read_rrd(path: str | Path, row_ids: bool = False) -> dict[str, list[dict]]:
    """entity path -> rows sorted by (lab_time, experiment, content); each row maps column -> value. ``row_ids``:
    each row also has its ``row_id`` (bytes that sort as the rows were logged: what orders rows of one instant)."""
    out: dict[str, list[dict]] = defaultdict(list)
    for chunk in RrdReader(path).store().stream():
        rb = chunk.to_record_batch()
        names = [n for n in rb.schema.names if n not in ("rerun.controls.RowId", "log_time", "log_tick")]
        cols = {n: _column(rb.column(n)) for n in names}
        ids = rb.column("rerun.controls.RowId").to_pylist() if row_ids else None
        for i in range(rb.num_rows):
            row = {n: _plain(cols[n][i]) for n in names if cols[n][i] is not None}
            if ids is not None:
                row["row_id"] = ids[i]
            out[chunk.entity_path.lstrip("/")].append(row)
    for rows in out.values():
        rows.sort(key=lambda r: (r.get("lab_time", -1), r.get("experiment", -1), repr(sorted(r.items()))))
    return dict(out)


def series(rows: list[dict], column: str = "Scalars:scalars") -> list[tuple[float, float]]:
    return [(r["lab_time"], r[column][0]) for r in rows if column in r]


def rerun_verify(path: str | Path) -> subprocess.CompletedProcess:
    """`rerun rrd verify PATH`: whether Rerun's own tools load the recording and read every column as its archetype
    says (exit 0), as the viewer will."""
    return subprocess.run([str(Path(sys.executable).parent / "rerun"), "rrd", "verify", str(path)],
                          capture_output=True, text=True, timeout=120)
