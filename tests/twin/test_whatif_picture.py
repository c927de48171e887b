"""What `--save` writes: a what-if's trade-offs as a picture (read back pixel by pixel), and a Rerun recording only
under a recording's name."""

from __future__ import annotations

import json

from tests.conftest import twin_cli
from tests.twin.test_whatif import FLAKY, ROOT, whatif


def test_a_picture_of_the_trade_offs_draws_each_variants_numbers(tmp_path):
    """`--save whatif.png` wrote a Rerun recording under the picture's name ("wrote whatif.png")."""
    from PIL import Image

    from twin.view.whatif_picture import bars_box, legend, utilisation_bars

    code, out = whatif(FLAKY, "--vary", "devices.reactor.instances=1,3", "--set", "campaign.budget=12",
                       "--set", "devices.reactor.cost=40", "--seeds", "2", "--json", "--save", str(tmp_path / "w.png"))
    assert code == 0, out
    summary = json.loads(out)["variants"]
    picture = Image.open(tmp_path / "w.png")
    assert picture.format == "PNG" and picture.width == 1200
    bars = utilisation_bars(summary, bars_box(summary))
    assert {(b.variant, b.device_type) for b in bars} == {(i, t) for i in range(3) for t in summary[0]["utilisation"]}
    for bar in bars:  # each bar stands as tall as its utilisation, in its type's colour
        use = summary[bar.variant]["utilisation"][bar.device_type]
        box = bars_box(summary)
        assert abs((bar.y1 - bar.y0) - use * (box[3] - box[1])) <= 1
        if bar.y1 - bar.y0 > 2:
            colour = "#%02X%02X%02X" % picture.getpixel(((bar.x0 + bar.x1) // 2, (bar.y0 + bar.y1) // 2))
            assert colour == bar.colour
    one, three = (next(r for r in summary if r["variant"] == f"devices.reactor.instances={n}") for n in (1, 3))
    reactor = [b for b in bars if b.device_type == "reactor"]
    assert reactor[summary.index(one)].y0 < reactor[summary.index(three)].y0  # one reactor is the busier
    lines = legend(summary, costs=True, seconds=False)
    assert lines[0].startswith("0: as written: lab-h >= ") and "cost " in lines[0] and "busiest reactor" in lines[0]


def test_a_recording_is_saved_only_under_a_recordings_name(tmp_path):
    """`twin run --save run.png` wrote a Rerun recording named as a picture."""
    res = twin_cli("run", FLAKY, "--save", str(tmp_path / "run.png"), columns=80)
    assert res.exit_code == 2 and f"this writes a Rerun recording, so name it {tmp_path / 'run.rrd'}" in \
        " ".join(res.output.split()), res.output
    assert not list(tmp_path.iterdir())


def test_the_picture_rings_the_variant_budget_hours_names(tmp_path):
    import numpy as np
    from PIL import Image

    from twin.view.whatif_picture import CHOSEN

    qd = str(ROOT / "scenarios" / "quantum_dots.yaml")
    code, out = whatif(qd, "--vary", "devices.synthesiser.instances=3", "--set", "devices.synthesiser.cost_per_hour=50",
                       "--seeds", "2", "--budget-hours", "50", "--json", "--save", str(tmp_path / "w.png"))
    assert code == 0, out
    named = json.loads(out)["cheapest_within"]
    assert named == "as written"  # two synthesisers cost less, and both meet the targets well within 50 lab-h
    red = [int(CHOSEN[i:i + 2], 16) for i in (1, 3, 5)]

    def reds(path):
        return int((np.asarray(Image.open(path).convert("RGB")) == red).all(axis=2).sum())

    assert reds(tmp_path / "w.png") > 50  # the ring and its line
    code, _ = whatif(qd, "--vary", "devices.synthesiser.instances=3", "--seeds", "1", "--save", str(tmp_path / "n.png"))
    assert code == 0 and reds(tmp_path / "n.png") == 0
