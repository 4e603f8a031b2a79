"""Time-to-quality of a training recipe: wall time and env steps until the deterministic policy
(the one ``export/`` ships) first reaches 90 % and 98 % end reached on the test split.

    python benchmarks/time_to_quality.py runs/iiwa_random              # read a finished run
    python benchmarks/time_to_quality.py --train runs/ttq -- --preset paper   # train, then read

Reads the run's ``progress.csv``: every evaluation during training runs the deterministic
(``eval/*``) and the sampled (``eval_sampled/*``) policy on the same ``eval_episodes`` test
sub-paths (a fixed key), with the policy/TOPP-RA duration ratio of those episodes. Prints, for
each policy and each bar, the first evaluation that met it (wall time incl. compilation, env
steps, end reached, ratio, mean deviation), or that it was never met, and the curves as a PNG
(``--plot FILE``). Training changes are judged by these numbers, not by env-steps/s alone.
"""

from __future__ import annotations

import argparse
import csv
import subprocess
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
BARS = (0.90, 0.98)
POLICIES = (("deterministic", "eval"), ("sampled", "eval_sampled"))


def read_progress(run: Path) -> list[dict[str, float]]:
    with open(run / "progress.csv", newline="") as f:
        return [{k: float(v) if v not in ("", None) else float("nan") for k, v in row.items()} for row in csv.DictReader(f)]


def first_reaching(rows: list[dict[str, float]], prefix: str, bar: float) -> dict[str, float] | None:
    """The first row whose ``prefix/end_reached`` is at least ``bar`` (None if none is)."""
    for row in rows:
        if row.get(f"{prefix}/end_reached", float("nan")) >= bar:
            return row
    return None


def report(run: Path) -> str:
    rows = read_progress(run)
    lines = [f"time to quality of {run} ({len(rows)} evaluations, last at step {int(rows[-1]['step']):,}, "
             f"{rows[-1]['wall_s'] / 60:.1f} min)"]
    for label, prefix in POLICIES:
        for bar in BARS:
            row = first_reaching(rows, prefix, bar)
            if row is None:
                best = max(r.get(f"{prefix}/end_reached", float("nan")) for r in rows)
                lines.append(f"  {label:13s} end reached >= {100 * bar:.0f} %: not reached (best {100 * best:.1f} %)")
            else:
                lines.append(f"  {label:13s} end reached >= {100 * bar:.0f} %: {row['wall_s'] / 60:6.1f} min, "
                             f"{int(row['step']):>12,} env steps  (end {100 * row[f'{prefix}/end_reached']:.1f} %, "
                             f"ratio to TOPP-RA {row.get(f'{prefix}/ratio_to_toppra', float('nan')):.3f}, "
                             f"mean deviation {row[f'{prefix}/mean_deviation']:.3f} rad)")
    last = rows[-1]
    for label, prefix in POLICIES:
        lines.append(f"  final {label:13s} end {100 * last[f'{prefix}/end_reached']:.1f} %  ratio "
                     f"{last.get(f'{prefix}/ratio_to_toppra', float('nan')):.3f}  deviation "
                     f"{last[f'{prefix}/mean_deviation']:.3f} rad")
    return "\n".join(lines)


def plot(runs: list[Path], file: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(11, 4))
    for run in runs:
        rows = read_progress(run)
        minutes = [r["wall_s"] / 60 for r in rows]
        for (label, prefix), style in zip(POLICIES, ("-", "--")):
            axes[0].plot(minutes, [100 * r[f"{prefix}/end_reached"] for r in rows], style, label=f"{run.name} {label}")
            axes[1].plot(minutes, [r.get(f"{prefix}/ratio_to_toppra", float("nan")) for r in rows], style,
                         label=f"{run.name} {label}")
    for bar in BARS:
        axes[0].axhline(100 * bar, color="grey", lw=0.5)
    axes[0].set(xlabel="wall time [min] (2 CPU cores)", ylabel="end reached [%]", ylim=(0, 101))
    axes[1].set(xlabel="wall time [min] (2 CPU cores)", ylabel="duration / TOPP-RA")
    axes[0].legend(fontsize=7)
    fig.tight_layout()
    file.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(file, dpi=110)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("runs", nargs="*", type=Path, help="run directories to read")
    parser.add_argument("--train", type=Path, default=None, metavar="RUN",
                        help="first train into RUN with train.py and the arguments after --")
    parser.add_argument("--plot", type=Path, default=None, help="PNG of the learning curves of all runs")
    args, train_args = parser.parse_known_args(argv)
    train_args = [a for a in train_args if a != "--"]
    runs = list(args.runs)
    if args.train is not None:
        result = subprocess.run([sys.executable, str(REPO / "train.py"), "--out", str(args.train), *train_args])
        if result.returncode:
            return result.returncode
        runs.append(args.train)
    if not runs:
        parser.error("give a run directory or --train RUN")
    for run in runs:
        print(report(run))
    if args.plot:
        plot(runs, args.plot)
        print(f"wrote {args.plot}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
