"""Joint-ranges per second: jitted batched safe range (4096 x 7) vs klimits (num_threads=1).

Run: python benchmarks/bench_limits.py [--batch 4096] [--dt 0.1]
Prints both throughputs and their ratio, measured in the same run on the same states.
"""

from __future__ import annotations

import argparse
import time

import numpy as np

import mjx_pathtrack

mjx_pathtrack.prepare_xla()  # before JAX starts: the CPU flag batched MJX needs
import jax

from mjx_pathtrack.robots import iiwa
from mjx_pathtrack.core import limits as L
from mjx_pathtrack.robots.iiwa import ACC, POS, VEL


def states(batch: int, seed: int = 0):
    rng = np.random.default_rng(seed)
    p = rng.uniform(-0.95, 0.95, (batch, 7)) * POS
    v = rng.uniform(-0.9, 0.9, (batch, 7)) * VEL
    a = rng.uniform(-0.9, 0.9, (batch, 7)) * ACC
    return p, v, a


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--batch", type=int, default=4096)
    parser.add_argument("--dt", type=float, default=0.1)
    parser.add_argument("--repeats", type=int, default=20)
    args = parser.parse_args()
    import klimits

    dt = args.dt
    jerk = 2.0 * ACC / dt
    p, v, a = states(args.batch)
    lim = iiwa.joint_limits(dt)
    fn = jax.jit(lambda p, v, a: L.safe_acceleration_range(lim, p, v, a, dt))
    pj, vj, aj = (jax.numpy.asarray(x, jax.numpy.float32) for x in (p, v, a))
    jax.block_until_ready(fn(pj, vj, aj))
    t0 = time.perf_counter()
    for _ in range(args.repeats):
        out = fn(pj, vj, aj)
    jax.block_until_ready(out)
    ours = args.repeats * p.size / (time.perf_counter() - t0)

    oracle = klimits.PosVelJerkLimitation(
        time_step=dt, pos_limits=np.stack([-POS, POS], 1), vel_limits=np.stack([-VEL, VEL], 1),
        acc_limits=np.stack([-ACC, ACC], 1), jerk_limits=np.stack([-jerk, jerk], 1),
        acceleration_after_max_vel_limit_factor=0.01, normalize_acc_range=False, num_threads=1)
    t0 = time.perf_counter()
    for i in range(args.batch):
        oracle.calculate_valid_acceleration_range(current_pos=p[i], current_vel=v[i], current_acc=a[i])
    theirs = p.size / (time.perf_counter() - t0)
    print(f"device: {jax.devices()[0].platform}  batch {args.batch} x 7  dt {dt}")
    print(f"mjx_pathtrack (jit, batched): {ours:14,.0f} joint-ranges/s")
    print(f"klimits (num_threads=1)     : {theirs:14,.0f} joint-ranges/s")
    print(f"ratio ours/klimits          : {ours / theirs:8.1f}x")


if __name__ == "__main__":
    main()
