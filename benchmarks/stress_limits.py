"""Stress the safe acceleration range far beyond what the test suite runs.

    python benchmarks/stress_limits.py                       # dt 0.4 s, seeds 0-9: >= 10^8 joint-steps
    python benchmarks/stress_limits.py --dt 0.1 --seeds 0,1 --episodes 512 --steps 200

For each seed: 7 joints with random limits whose jerk limit binds (jerk = f 2 acc / dt, f in
[0.1, 0.9]) and whose position corridors go down to +-0.2 rad (``tests/limit_rollouts.py``),
jitted and vmapped as in training:

- ``--episodes`` closed-loop episodes from rest at random positions, split evenly over the
  policies random, +1, -1, bang-bang (period 1-8), push-to-limit and chatter (random sign
  every step), ``--steps`` decisions each;
- the border family: every start on and 1-4 float32 ulps beyond each position / velocity /
  acceleration limit (``border_states``), every policy, ``--border-repeats`` draws each.

Every step is checked at its start, end and exact extrema inside (``limits.step_extrema``).
A *violation* is a joint-step whose usage of any limit exceeds 1 + ``--tolerance`` (border
starts: their own start usage + tolerance); steps the range flags (violation / empty range)
are counted too. Prints the counts per seed and in all; exits 1 on any violation or flag.
"""

from __future__ import annotations

import argparse
import pathlib
import sys
import time

sys.path.insert(0, str(pathlib.Path(__file__).resolve().parents[1] / "tests"))

import jax  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

from limit_rollouts import COMPONENTS, POLICIES, border_usage, closed_loop, random_limits  # noqa: E402


def random_starts(limits, episodes: int, seed: int):
    """Rest at uniform positions (2-98 % of each corridor), policies evenly, periods 1-8."""
    k0, k1, k2 = jax.random.split(jax.random.PRNGKey(seed), 3)
    n = limits.n_joints
    span = limits.pos_max - limits.pos_min
    p0 = limits.pos_min + span * jax.random.uniform(k0, (episodes, n), minval=0.02, maxval=0.98)
    policy = np.arange(episodes) % len(POLICIES)
    return p0, jnp.zeros((episodes, n)), jnp.zeros((episodes, n)), policy, jax.random.randint(k1, (episodes,), 1, 9), \
        jax.random.split(k2, episodes)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--dt", type=float, default=0.4)
    parser.add_argument("--seeds", default="0,1,2,3,4,5,6,7,8,9")
    parser.add_argument("--episodes", type=int, default=4096, help="random-start episodes per seed")
    parser.add_argument("--steps", type=int, default=500, help="decisions per random-start episode")
    parser.add_argument("--border-repeats", type=int, default=16)
    parser.add_argument("--border-steps", type=int, default=100)
    parser.add_argument("--tolerance", type=float, default=1e-5, help="relative")
    args = parser.parse_args(argv)
    total_steps = total_over = total_flagged = 0
    for seed in (int(s) for s in args.seeds.split(",")):
        t0 = time.time()
        limits = random_limits(args.dt, seed=seed)
        n = limits.n_joints
        usage, width, flagged, over = closed_loop(limits, args.dt, *random_starts(limits, args.episodes, seed),
                                                  args.steps, threshold=1.0 + args.tolerance)
        excess, b_flagged, b_width, _, b_over = border_usage(limits, args.dt, args.border_repeats, args.border_steps,
                                                             seed=seed, tolerance=args.tolerance)
        steps = args.episodes * args.steps * n + len(excess) * args.border_steps * n
        bad_over, bad_flag = int(over.sum() + b_over.sum()), int(flagged.sum() + b_flagged.sum())
        total_steps, total_over, total_flagged = total_steps + steps, total_over + bad_over, total_flagged + bad_flag
        worst = usage.max(axis=(0, 2))
        worst_border = excess.max(axis=(0, 2))
        print(f"dt {args.dt} seed {seed}: {steps:,} joint-steps, violations beyond {args.tolerance:g}: {bad_over}, "
              f"flagged: {bad_flag}, min width {min(width.min(), b_width.min()):.3g}; worst usage "
              + " ".join(f"{c[:3]} {x:.7f}" for c, x in zip(COMPONENTS, worst))
              + "; border starts, beyond their start: " + " ".join(f"{c[:3]} {x:.2e}" for c, x in zip(COMPONENTS, worst_border))
              + f"  ({time.time() - t0:.0f} s)", flush=True)
    print(f"total: {total_steps:,} joint-steps, {total_over} violations beyond {args.tolerance:g} relative, "
          f"{total_flagged} flagged steps")
    return 1 if total_over or total_flagged else 0


if __name__ == "__main__":
    sys.exit(main())
