"""The reactor's heater: PID against PPO (pure) and PID + PPO (residual), per set-point.

    .venv/bin/python bench/bench_reactor_control.py [--pure P.zip] [--residual P.zip]

Each controller heats the catalyst reactor from ambient to the set-point and
holds it for an hour in the reactor's own thermal model (exotherm included).
Columns: time to the ±2 K band, overshoot, RMS error once there, and the
catalyst's yield and selectivity from that temperature trace. The second
table runs the same controllers on a reactor unlike the one they were tuned
or trained on.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import torch

from devices.models import thermal
from devices.reactor import load_controller
from devices.reactor_control import PolicyController
from devices.train_controller import compare

ROOT = Path(__file__).resolve().parents[1]
GAINS = {"kp": 6.0, "ki": 0.04}  # scenarios/catalyst.yaml
PLANTS = {"the reactor as modelled (the policies were trained on it)": thermal.NOMINAL,
          "a mismatched reactor: 50 % slower, heater 25 % weaker, exotherm doubled":
              thermal.Plant(tau_s=450.0, u_max_k=300.0, exotherm_k=12.0)}
METRICS = [("time_to_target_s", "time to ±2 K (s)", "{:.0f}"), ("overshoot_k", "overshoot (K)", "{:.2f}"),
           ("rms_k", "RMS once there (K)", "{:.2f}"), ("yield", "yield %", "{:.1f}"),
           ("selectivity", "selectivity %", "{:.1f}")]


def main() -> None:
    torch.set_num_threads(1)
    ap = argparse.ArgumentParser()
    ap.add_argument("--pure", type=Path, default=ROOT / "devices/policies/reactor_pure.zip")
    ap.add_argument("--residual", type=Path, default=ROOT / "devices/policies/reactor_residual.zip")
    args = ap.parse_args()
    controllers = {"pid": lambda sp: thermal.Pid(**GAINS)}
    for label, path in (("ppo", args.pure), ("pid+ppo", args.residual)):
        policy, mode = load_controller(path)
        controllers[label] = lambda sp, p=policy, m=mode: PolicyController(p, sp, m, thermal.Pid(**GAINS))
    for title, plant in PLANTS.items():
        print(f"\n## {title}")
        table(compare(controllers, plant=plant))


def table(results: dict) -> None:
    setpoints = list(next(iter(results.values())))
    print(f"{'set-point':>10} {'controller':>10} " + " ".join(f"{h:>20}" for _, h, _ in METRICS))
    for sp in setpoints:
        for name, rows in results.items():
            cells = " ".join(f"{fmt.format(rows[sp][k]):>20}" for k, _, fmt in METRICS)
            print(f"{sp if isinstance(sp, str) else f'{sp:.0f} K':>10} {name:>10} {cells}")
    print("\nratio to pid (mean over set-points; < 1 is better for the first three, > 1 for the last two)")
    base = results["pid"]["mean"]
    for name, rows in results.items():
        print(f"{name:>10} " + " ".join(f"{rows['mean'][k] / base[k] if base[k] else float('nan'):>20.2f}"
                                        for k, _, _ in METRICS))


if __name__ == "__main__":
    main()
