"""`twin whatif --save X.png`: the trade-offs as one picture, to paste into a report (Pillow: rerun-sdk's own).

Left, each variant's lab-hours to target (median, its IQR as a whisker) against its median cost — or, where
nothing costs anything, against its number; a hollow point did not meet every target in every run. Right, each
device type's mean utilisation per variant. Below, a line per variant: its number, what it changes, its numbers and
its busiest device type (the bottleneck).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from PIL import Image, ImageDraw, ImageFont

from twin.core.counts import counted

WIDTH, PANEL_H, LINE_H, MARGIN = 1200, 440, 20, 60
CHOSEN = "#E45756"
PALETTE = ["#4C78A8", "#F58518", "#54A24B", "#E45756", "#72B7B2", "#B279A2", "#FF9DA6", "#9D755D", "#BAB0AC",
           "#EECA3B"]


@dataclass(frozen=True)
class Bar:
    """One device type's utilisation in one variant, as drawn: its box in pixels and its colour."""

    variant: int
    device_type: str
    x0: int
    y0: int
    x1: int
    y1: int
    colour: str


def _nice_ticks(lo: float, hi: float, count: int = 5) -> list[float]:
    if not hi > lo:
        hi = lo + 1.0
    raw = (hi - lo) / count
    step = 10 ** math.floor(math.log10(raw))
    step *= next(m for m in (1, 2, 2.5, 5, 10) if raw <= m * step)
    first = math.floor(lo / step) * step
    return [first + i * step for i in range(int(math.ceil((hi - first) / step)) + 1)]


def _types(summary: list[dict[str, Any]]) -> list[str]:
    return sorted({t for row in summary for t in row["utilisation"]})


def utilisation_bars(summary: list[dict[str, Any]], box: tuple[int, int, int, int]) -> list[Bar]:
    """The right panel's bars inside ``box`` (x0, y0, x1, y1): a group per variant, a bar per device type, its
    height its utilisation (100 % is the box's height)."""
    x0, y0, x1, y1 = box
    types = _types(summary)
    group = (x1 - x0) / max(1, len(summary))
    width = max(1.0, 0.8 * group / max(1, len(types)))
    out = []
    for i, row in enumerate(summary):
        for j, name in enumerate(types):
            left = x0 + i * group + 0.1 * group + j * width
            top = y1 - round((y1 - y0) * min(1.0, max(0.0, row["utilisation"].get(name, 0.0))))
            out.append(Bar(i, name, round(left), top, round(left + width) - 1, y1, PALETTE[j % len(PALETTE)]))
    return out


def _frame(draw: ImageDraw.ImageDraw, box: tuple[int, int, int, int], title: str, font: Any) -> None:
    draw.rectangle(box, outline="#888888")
    draw.text((box[0], box[1] - 22), title, fill="black", font=font)


def bars_box(summary: list[dict[str, Any]]) -> tuple[int, int, int, int]:
    """Where the utilisation bars of a picture of ``summary`` stand (100 % is its top)."""
    half = (WIDTH - 3 * MARGIN) // 2
    return 2 * MARGIN + half + 20, MARGIN + 60, WIDTH - MARGIN - 10, MARGIN + PANEL_H - 50


def save_whatif_png(path: str | Path, scenario: str, summary: list[dict[str, Any]], seeds: int,
                    costs: bool, seconds: bool, targets: bool = True,
                    chosen: tuple[int, float] | None = None) -> None:
    """The picture of ``summary`` (the rows `twin whatif --json` prints as ``variants``) as a PNG at ``path``;
    ``costs``: something costs (else variants are placed by number); ``seconds``: read in lab-seconds;
    ``targets``: the lab has targets (else its hours are to the campaign's end); ``chosen``: the variant
    `--budget-hours H` named and H, ringed and said."""
    font, small = ImageFont.load_default(size=15), ImageFont.load_default(size=12)
    image = Image.new("RGB", (WIDTH, MARGIN + PANEL_H + 30 + LINE_H * (len(summary) + 3)), "white")
    draw = ImageDraw.Draw(image)
    draw.text((MARGIN, 12), f"{scenario}: what if - {len(summary)} variants x {counted(seeds, 'seed', 'seeds')}, "
              "medians [IQR]", fill="black", font=font)
    unit, scale = ("lab-s", 3600.0) if seconds else ("lab-h", 1.0)
    half = (WIDTH - 3 * MARGIN) // 2
    left = (MARGIN + 10, MARGIN + 30, MARGIN + 10 + half - 10, MARGIN + 30 + PANEL_H - 60)
    right = (2 * MARGIN + half + 10, left[1], WIDTH - MARGIN, left[3])
    _frame(draw, left, f"{unit} to {'target' if targets else 'the end'} against " + ("cost" if costs else "variant"),
           font)
    _frame(draw, right, "utilisation per device type (mean)", font)

    xs = [row["cost"][1] if costs else float(i) for i, row in enumerate(summary)]
    ys = [v * scale for row in summary for v in (row["lab_hours"][0], row["lab_hours"][2])]
    xt, yt = _nice_ticks(min(xs), max(xs)), _nice_ticks(min(0.0, min(ys)), max(ys))
    (px0, py0, px1, py1), pad = left, 20

    def at(x: float, y: float) -> tuple[float, float]:
        return (px0 + pad + (px1 - px0 - 2 * pad) * (x - xt[0]) / (xt[-1] - xt[0]),
                py1 - pad - (py1 - py0 - 2 * pad) * (y - yt[0]) / (yt[-1] - yt[0]))

    for y in yt:
        _, v = at(xt[0], y)
        draw.line((px0, v, px0 + 5, v), fill="#888888")
        draw.text((px0 - 8, v), f"{y:g}", fill="black", font=small, anchor="rm")
    for x in xt if costs else range(len(summary)):
        u, _ = at(x, yt[0])
        draw.line((u, py1, u, py1 - 5), fill="#888888")
        draw.text((u, py1 + 4), f"{x:,.0f}" if costs else str(x), fill="black", font=small, anchor="mt")
    labels: dict[tuple[int, int], tuple[float, float, list[str]]] = {}  # variants at one spot share a label: "1, 2"
    for i, (row, x) in enumerate(zip(summary, xs)):
        q1, median, q3 = (v * scale for v in row["lab_hours"])
        u, v = at(x, median)
        draw.line((u, at(x, q1)[1], u, at(x, q3)[1]), fill="#444444", width=2)
        met = not targets or row["reached"] == row["runs"]
        draw.ellipse((u - 5, v - 5, u + 5, v + 5), outline="black", fill="black" if met else "white", width=2)
        if chosen is not None and i == chosen[0]:
            draw.ellipse((u - 10, v - 10, u + 10, v + 10), outline=CHOSEN, width=3)
        labels.setdefault((round(u / 6), round(v / 6)), (u, v, []))[2].append(str(i))
    for u, v, names in labels.values():
        draw.text((u + 10, v), ", ".join(names), fill="black", font=small, anchor="lm")

    types = _types(summary)
    box = bars_box(summary)
    for share in (0.0, 0.5, 1.0):
        v = box[3] - share * (box[3] - box[1])
        draw.line((right[0], v, right[0] + 5, v), fill="#888888")
        draw.text((right[0] - 8, v), f"{100 * share:.0f} %", fill="black", font=small, anchor="rm")
    bars = utilisation_bars(summary, box)
    for bar in bars:
        draw.rectangle((bar.x0, bar.y0, bar.x1, bar.y1), fill=bar.colour)
    for i in range(len(summary) if types else 0):
        group = [b for b in bars if b.variant == i]
        draw.text(((group[0].x0 + group[-1].x1) / 2, right[3] - 18), str(i), fill="black", font=small, anchor="mt")
    x = right[0] + 10
    for j, name in enumerate(types):
        draw.rectangle((x, right[1] + 8, x + 12, right[1] + 20), fill=PALETTE[j % len(PALETTE)])
        draw.text((x + 16, right[1] + 6), name, fill="black", font=small)
        x += 24 + int(draw.textlength(name, font=small))

    y = MARGIN + PANEL_H + 10
    draw.text((MARGIN, y), ("a hollow point did not meet every target in every run; " if targets else "") +
              "numbers: medians [IQR]", fill="#444444", font=small)
    for i, line in enumerate(legend(summary, costs, seconds, targets)):
        draw.text((MARGIN, y + LINE_H * (i + 1)), line[:170], fill="black", font=small)
    if chosen is not None:
        draw.text((MARGIN, y + LINE_H * (len(summary) + 1)),
                  f"ringed: {'the cheapest' if costs else 'the fastest'} within {chosen[1]:g} lab-h "
                  f"(median; every target met in every run): {chosen[0]}", fill=CHOSEN, font=small)
    Path(path).parent.mkdir(parents=True, exist_ok=True)
    image.save(path, format="PNG")


def legend(summary: list[dict[str, Any]], costs: bool, seconds: bool, targets: bool = True) -> list[str]:
    """A line per variant, as the picture's bottom says it (">=": not met in every run, as the table's "≥")."""
    unit, scale = ("lab-s", 3600.0) if seconds else ("lab-h", 1.0)
    out = []
    for i, row in enumerate(summary):
        q1, median, q3 = (v * scale for v in row["lab_hours"])
        busiest = row["bottleneck"]
        short = ">= " if targets and row["reached"] < row["runs"] else ""
        spread = f" [{q1:,.4g} to {q3:,.4g}]" if q3 > q1 else ""
        line = (f"{i}: {row['variant']}: {unit} {short}{median:,.4g}{spread}"
                + (f", cost {row['cost'][1]:,.0f}" if costs else "")
                + (f", busiest {busiest} {100 * row['utilisation'].get(busiest, 0.0):.0f} %" if busiest else ""))
        out.append(line)
    return out
