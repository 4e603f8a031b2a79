"""Stress the safe acceleration range with more random limit draws than the test suite runs.

    python benchmarks/stress_limits.py --dt 0.4 --seeds 0,1,2,4 [--episodes 200] [--steps 100]

For each seed: random joint limits whose jerk limit binds and whose position corridors go down
to +-0.2 rad (``tests/limit_rollouts.random_limits``), ``episodes`` closed-loop episodes per
policy (random, +1, -1, bang-bang, adversarial), checked at every step and at the exact extrema
inside each step. Prints the worst normalised usage per policy and exits 1 on any violation.
"""

from __future__ import annotations

import argparse
import pathlib
import sys
import time

sys.path.insert(0, str(pathlib.Path(__file__).resolve().parents[1] / "tests"))

from limit_rollouts import random_limits, rollout_usage  # noqa: E402


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--dt", type=float, default=0.4)
    parser.add_argument("--seeds", default="0,1,2,4")
    parser.add_argument("--episodes", type=int, default=200, help="episodes per policy")
    parser.add_argument("--steps", type=int, default=100)
    args = parser.parse_args(argv)
    bad = 0
    for seed in (int(s) for s in args.seeds.split(",")):
        t0 = time.time()
        results = rollout_usage(random_limits(args.dt, seed=seed), args.dt, args.episodes, args.steps, seed=seed)
        for policy, (usage, width, violations) in results.items():
            worst = usage.max(1)
            broken = bool((worst > 1.0 + 1e-6).any() or violations or width < 0)
            bad += broken
            print(f"dt {args.dt} seed {seed} {policy:12s} max usage p/v/a/jerk {worst.round(6)} "
                  f"min width {width:.3g} flagged {violations}{'  VIOLATION' if broken else ''}")
        print(f"seed {seed}: {time.time() - t0:.0f} s", flush=True)
    print("OK" if not bad else f"{bad} policy/seed cases violated a limit")
    return 1 if bad else 0


if __name__ == "__main__":
    sys.exit(main())
