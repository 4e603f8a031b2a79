"""Paper 001 experiments on the velocity-maximisation task: Table II (trained vs optimal average
velocity per decision frequency) and Table I (penalty baselines vs the safe action space).

    python scripts/paper001_experiments.py --out runs/paper001            # all runs (1,480 s on 2 CPU cores shared with other runs)
    python scripts/paper001_experiments.py --out runs/paper001 --tables-only   # rebuild tables from reports

Runs PPO (:mod:`mjx_pathtrack.rl.velocity_max_train`) for ``mode="safe"`` at 10, 20, 120 and
240 Hz and for ``penalty_soft`` / ``penalty_hard`` at 20 and 240 Hz (Table I's frequencies), one
run directory each (``<out>/<mode>_<hz>``); a run whose ``report.json`` exists for the same config
is reused. Writes ``<out>/results.json`` and ``<out>/tables.md``. Budgets (env steps per run) fit
one CPU session, below the paper's training until convergence; the tables say how many episodes
each policy saw. The penalty baselines get the budget of the safe run at their frequency. Every
run bounds its policy mean (``--mean-clip``, default 1.0 as in ``VelocityTrainConfig``).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
import time
from pathlib import Path

from mjx_pathtrack.fileio import atomic_write_bytes  # first: CPU XLA flags before JAX starts
from mjx_pathtrack.envs.tasks import velocity_max as V
from mjx_pathtrack.rl import velocity_max_train as T

#: env steps per run at each frequency (scaled by --budget-scale)
BUDGET = {10: 750_000, 20: 1_000_000, 120: 10_000_000, 240: 12_000_000}
#: Table I frequencies (paper 001)
PENALTY_FREQUENCIES = (240, 20)
#: paper 001 Table II (average velocity: random, trained, optimal) and Table I (avg velocity,
#: violation rate, max position, max velocity) for reference in the tables
PAPER_TABLE2 = {240: (0.212, 0.912, 0.921), 120: (0.268, 0.908, 0.920), 20: (0.431, 0.880, 0.919),
                10: (0.487, 0.865, 0.913)}
PAPER_TABLE1 = {(240, "safe"): (0.91, 0.0, 1.00, 1.00), (240, "penalty_soft"): (0.51, 0.080, 1.25, 0.90),
                (240, "penalty_hard"): (0.71, 0.527, 1.43, 1.56), (20, "safe"): (0.88, 0.0, 1.00, 1.00),
                (20, "penalty_soft"): (0.44, 0.012, 0.93, 1.14), (20, "penalty_hard"): (0.58, 0.415, 1.14, 1.69)}


def plan(budget_scale: float, seed: int, mean_clip: float | None = 1.0) -> list[T.VelocityTrainConfig]:
    def run(hz, mode):
        return T.VelocityTrainConfig.from_flat(dict(hz=hz, mode=mode, num_timesteps=int(BUDGET[hz] * budget_scale),
                                                    seed=seed, mean_clip=mean_clip))

    runs = [run(hz, "safe") for hz in V.FREQUENCIES]
    runs += [run(hz, mode) for hz in PENALTY_FREQUENCIES for mode in ("penalty_soft", "penalty_hard")]
    return runs


def run_dir(out: Path, config: T.VelocityTrainConfig) -> Path:
    return out / f"{config.mode}_{config.hz:g}"


def load_report(directory: Path, config: T.VelocityTrainConfig) -> dict | None:
    """The saved report of ``directory`` if it was made with exactly ``config``."""
    try:
        saved = T.VelocityTrainConfig.from_json((directory / "config.json").read_text())
        report = json.loads((directory / "report.json").read_text())
    except (OSError, ValueError):
        return None
    return report if saved == config else None


def tables(results: dict[str, dict]) -> str:
    """Markdown for Table II and Table I from ``results[name] = {"config", "report"}``."""
    def get(hz, mode):
        return next((r for r in results.values() if r["config"]["hz"] == hz and r["config"]["mode"] == mode), None)

    lines = ["Table II -- average velocity (mean |v| / v_max over joints and 5 s; safe action space)", "",
             "| frequency | random | trained | optimal (searched) | trained / optimal | episodes trained "
             "| paper: random / trained / optimal |", "|---|---|---|---|---|---|---|"]
    for hz in sorted(V.FREQUENCIES, reverse=True):
        r = get(hz, "safe")
        if r is None:
            continue
        rep = r["report"]
        rnd, tr, opt = (rep[k]["avg_velocity"] for k in ("random", "trained", "optimal"))
        paper = " / ".join(f"{x:.3f}" for x in PAPER_TABLE2[hz])
        lines.append(f"| {hz} Hz | {rnd:.3f} | {tr:.3f} | {opt:.3f} | {tr / opt:.3f} | "
                     f"{rep['episodes_trained']:,} | {paper} |")
    lines += ["", "Table I -- trained policies, safe action space vs reward penalties", "",
              "| frequency | method | average velocity | violation rate | max. position | max. velocity "
              "| episodes trained | paper: avg vel / viol. rate / max pos / max vel |", "|---|---|---|---|---|---|---|---|"]
    names = {"safe": "ours (safe action space)", "penalty_soft": "soft penalties", "penalty_hard": "hard penalties"}
    for hz in PENALTY_FREQUENCIES:
        for mode in ("safe", "penalty_soft", "penalty_hard"):
            r = get(hz, mode)
            if r is None:
                continue
            m = r["report"]["trained"]
            p = PAPER_TABLE1[(hz, mode)]
            lines.append(f"| {hz} Hz | {names[mode]} | {m['avg_velocity']:.3f} | {m['violation_rate']:.1%} | "
                         f"{m['max_position']:.2f} | {m['max_velocity']:.2f} | {r['report']['episodes_trained']:,} | "
                         f"{p[0]:.2f} / {p[1]:.1%} / {p[2]:.2f} / {p[3]:.2f} |")
    return "\n".join(lines) + "\n"


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--out", default="runs/paper001")
    parser.add_argument("--budget-scale", type=float, default=1.0, help="multiply every run's env steps")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--mean-clip", type=T.optional_float, default=T.VelocityTrainConfig().network.mean_clip,
                        help="bound of the policy mean for every run ('none': unbounded)")
    parser.add_argument("--only", nargs="+", default=None, help="run names to do, e.g. safe_10 penalty_soft_240")
    parser.add_argument("--tables-only", action="store_true", help="only rebuild the tables from saved reports")
    args = parser.parse_args(argv)
    if args.budget_scale <= 0:
        parser.error("--budget-scale must be > 0")
    out = Path(args.out)
    results: dict[str, dict] = {}
    t0 = time.monotonic()
    for config in plan(args.budget_scale, args.seed, args.mean_clip):
        directory = run_dir(out, config)
        name = directory.name
        report = load_report(directory, config)
        if report is None and not args.tables_only and (args.only is None or name in args.only):
            print(f"== {name}: {config.num_timesteps:,} env steps", flush=True)
            t = time.monotonic()
            _, _, report = T.train(config, directory, verbose=True)
            print(f"== {name} done in {time.monotonic() - t:.0f} s", flush=True)
        if report is not None:
            results[name] = {"config": dataclasses.asdict(config), "report": report}
    text = tables(results)
    atomic_write_bytes(out / "results.json", (json.dumps(results, indent=2) + "\n").encode())
    atomic_write_bytes(out / "tables.md", text.encode())
    print(text)
    print(f"total wall time {time.monotonic() - t0:.0f} s", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
