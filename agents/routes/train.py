"""Train the route search's expansion prior: ``python -m agents.routes.train --targets 2000 --out P``.

Makes ``--targets`` training targets forwards from the stock (depths 1–6; seeds the held-out set never uses),
teaches the template scorer every step of their routes (``agents.routes.policy``), and reports how often its
first and first five templates are the right ones on the steps of 100 held-out targets. Writes ``P.pt`` and
``P.json`` (the template names it scores, and these numbers).
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from pathlib import Path

import torch

from agents.routes import stock as stock_file
from agents.routes import templates as template_file
from agents.routes.policy import LearnedPrior, examples, save_prior, train_prior
from agents.routes.targets import target_set


def accuracy(prior: LearnedPrior, pairs: list[tuple[str, str]]) -> tuple[float, float]:
    top1 = statistics.mean(prior.ranked(m)[0] == name for m, name in pairs)
    top5 = statistics.mean(name in prior.ranked(m)[:5] for m, name in pairs)
    return top1, top5


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(prog="python -m agents.routes.train", description=__doc__.split("\n\n")[0])
    ap.add_argument("--targets", type=int, default=2000, help="training targets to make (default 2000)")
    ap.add_argument("--epochs", type=int, default=30)
    ap.add_argument("--out", type=Path, required=True, help="where to write P.pt and P.json")
    ap.add_argument("--templates", type=Path, default=template_file.TEMPLATES)
    ap.add_argument("--stock", type=Path, default=stock_file.STOCK)
    args = ap.parse_args(argv)
    torch.set_num_threads(1)
    t0 = time.perf_counter()
    templates, stock = template_file.load(args.templates), stock_file.load(args.stock)
    train = target_set(templates, stock, args.targets)
    pairs = examples(train)
    print(f"{len(train)} training targets, {len(pairs)} route steps ({time.perf_counter() - t0:.0f} s)", file=sys.stderr)
    scorer = train_prior(templates, pairs, epochs=args.epochs,
                         on_epoch=lambda e, loss: print(f"epoch {e:3}  loss {loss:.3f}", file=sys.stderr))
    held = examples(target_set(templates, stock, 100, held_out=True))
    top1, top5 = accuracy(LearnedPrior(scorer, [t.name for t in templates]), held)
    save_prior(scorer, templates, args.out, targets=len(train), steps=len(pairs), epochs=args.epochs,
               held_out_top1=round(top1, 3), held_out_top5=round(top5, 3),
               command=f"python -m agents.routes.train --targets {args.targets} --epochs {args.epochs} --out {args.out}")
    print(f"held-out steps {len(held)}: the right template first {top1:.0%}, in the first five {top5:.0%}; "
          f"saved {args.out.with_suffix('.pt')} ({time.perf_counter() - t0:.0f} s)")


if __name__ == "__main__":
    main()
