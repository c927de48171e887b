"""What the environments draw for ``render_mode="rgb_array"`` — what Stable-Baselines3's ``make_vec_env`` asks of
every environment, and what a video recorder records: small RGB pictures as ``(height, width, 3)`` uint8 arrays."""

from __future__ import annotations

import numpy as np

WIDTH, ROW_H, MARGIN = 480, 14, 6
STATE_COLOURS = {"busy": (84, 162, 75), "idle": (76, 120, 168), "offline": (128, 128, 128),
                 "quarantined": (245, 133, 24)}
GOOD, BAD = (84, 162, 75), (228, 87, 86)
RENDER_MODES = ("rgb_array",)
METADATA = {"render_modes": list(RENDER_MODES), "render_fps": 4}  # a picture per decision; the fps is a video's


def render_mode_of(render_mode: str | None) -> str | None:
    """``render_mode`` checked: ``None`` (nothing drawn) or ``"rgb_array"``."""
    if render_mode not in (None, *RENDER_MODES):
        raise ValueError(f"render_mode {render_mode!r}: this environment draws rgb_array pictures (or give None)")
    return render_mode


class Spans:
    """Each device's states over lab time, as (start, end, state) spans, from snapshots taken at each decision."""

    def __init__(self) -> None:
        self.rows: dict[str, list[list]] = {}
        self.now = 0.0

    def snapshot(self, now: float, states: dict[str, str]) -> None:
        self.now = now
        for name, state in states.items():
            row = self.rows.setdefault(name, [])
            if row:
                row[-1][1] = now
            if not row or row[-1][2] != state:
                row.append([now, now, state])

    def picture(self) -> np.ndarray:
        """A row per device, lab time left to right (0 to now), each span in its state's colour."""
        from PIL import Image, ImageDraw  # only when drawn: ~40 ms of imports a training never needs

        names = sorted(self.rows)
        image = Image.new("RGB", (WIDTH, 2 * MARGIN + ROW_H * max(1, len(names))), "white")
        draw = ImageDraw.Draw(image)
        scale = (WIDTH - 2 * MARGIN) / self.now if self.now > 0 else 0.0
        for i, name in enumerate(names):
            top = MARGIN + i * ROW_H
            for start, end, state in self.rows[name]:
                x0, x1 = MARGIN + start * scale, MARGIN + max(end * scale, start * scale + 1)
                draw.rectangle((x0, top + 1, x1, top + ROW_H - 2), fill=STATE_COLOURS.get(state, (0, 0, 0)))
        return np.asarray(image, dtype=np.uint8)


def points_picture(points: list[tuple[float, float, float]], best: int | None, size: int = 240) -> np.ndarray:
    """Points in the unit square (x, y, badness in [0, 1]: green when 0, red when 1), the ``best`` one ringed."""
    from PIL import Image, ImageDraw

    image = Image.new("RGB", (size, size), "white")
    draw = ImageDraw.Draw(image)
    inner = size - 2 * MARGIN
    draw.rectangle((MARGIN, MARGIN, MARGIN + inner, MARGIN + inner), outline=(200, 200, 200))
    for i, (x, y, bad) in enumerate(points):
        u, v = MARGIN + x * inner, MARGIN + (1.0 - y) * inner
        bad = min(1.0, max(0.0, bad))
        colour = tuple(int(g + (r - g) * bad) for g, r in zip(GOOD, BAD))
        draw.ellipse((u - 4, v - 4, u + 4, v + 4), fill=colour)
        if i == best:
            draw.ellipse((u - 6, v - 6, u + 6, v + 6), outline="black", width=2)
    return np.asarray(image, dtype=np.uint8)
