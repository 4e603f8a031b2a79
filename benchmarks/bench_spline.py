"""Path queries per second: jitted, vmapped ``point_at`` + ``knot_window`` over a batch of paths.

Run: python benchmarks/bench_spline.py [--batch 4096] [--knots 200] [--window 8]

Each environment has its own path (200 knots, 7 joints; 64 distinct paths tiled over the batch)
and its own arc position. One "evaluation" = one position at s plus the knot window at s for
one environment. The reference is what the papers' code does per environment (one SciPy spline
object each): arc length -> parameter by linear interpolation in the (u, s) table, then
``CubicSpline.__call__``; measured on the same paths and positions in the same run, so the
printed ratio is meaningful on this machine only.
"""

from __future__ import annotations

import argparse
import time

import numpy as np

import mjx_pathtrack

mjx_pathtrack.prepare_xla()  # before JAX starts: the CPU flag batched MJX needs
import jax
import jax.numpy as jnp

from mjx_pathtrack.core import spline as S


def random_knots(n_knots: int, rng: np.random.Generator) -> np.ndarray:
    """A smooth-ish joint-space path: random walk with ~0.15 rad steps, 7 joints."""
    return np.cumsum(rng.normal(0.0, 0.06, (n_knots, 7)), axis=0)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--batch", type=int, default=4096)
    parser.add_argument("--knots", type=int, default=200)
    parser.add_argument("--window", type=int, default=8)
    parser.add_argument("--distinct", type=int, default=64)
    parser.add_argument("--repeats", type=int, default=50)
    args = parser.parse_args()
    rng = np.random.default_rng(0)

    fits = [S.fit_spline(random_knots(args.knots, rng)) for _ in range(args.distinct)]
    which = np.arange(args.batch) % args.distinct
    batch = jax.tree_util.tree_map(lambda x: x[which], S.stack_fits(fits, args.knots))
    lengths = np.array([f.length for f in fits])[which]
    s = rng.uniform(0.0, 1.0, (args.repeats, args.batch)) * lengths

    def query(path, s):
        w = S.knot_window(path, s, args.window)
        return S.point_at(path, s), w.knots, w.knot_distances, w.offset

    fn = jax.jit(jax.vmap(query))
    s_dev = [jnp.asarray(x, jnp.float32) for x in s]
    jax.block_until_ready(fn(batch, s_dev[0]))
    t0 = time.perf_counter()
    for x in s_dev:
        out = fn(batch, x)
    jax.block_until_ready(out)
    ours = args.repeats * args.batch / (time.perf_counter() - t0)

    # per-environment SciPy evaluation, as in the papers' code
    splines = [f.scipy_spline() for f in fits]
    tables_u = []   # global chord parameter at each arc-length table point
    for f in fits:
        m, j = f.samples_per_segment, np.arange(len(f.h) * f.samples_per_segment + 1)
        u0 = np.concatenate([[0.0], np.cumsum(f.h)])
        tables_u.append(u0[j // m] + (j % m) * np.append(f.h, 0.0)[j // m] / m)
    n_ref = min(args.batch, 2048)
    t0 = time.perf_counter()
    for i in range(n_ref):
        k = which[i]
        u = np.interp(s[0, i], fits[k].table_s, tables_u[k])
        splines[k](u)
        j = np.searchsorted(fits[k].knot_s, s[0, i], side="right") - 1
        idx = np.minimum(j + np.arange(args.window + 1), len(fits[k].knot_s) - 1)
        fits[k].knots[idx]
    theirs = n_ref / (time.perf_counter() - t0)
    check = np.stack([fits[which[i]].point_at(s[-1, i]) for i in range(256)])
    err = np.abs(np.asarray(out[0][:256], np.float64) - check).max()
    print(f"device: {jax.devices()[0].platform}  batch {args.batch}  paths of {args.knots} knots x 7 joints  "
          f"window {args.window}  M = {batch.samples_per_segment}")
    print(f"mjx_pathtrack point_at + knot_window (jit, vmap): {ours:14,.0f} evaluations/s")
    print(f"SciPy per-environment interp + CubicSpline:       {theirs:14,.0f} evaluations/s")
    print(f"ratio: {ours / theirs:.0f}x   (max |JAX float32 - NumPy float64| position: {err:.1e} rad)")


if __name__ == "__main__":
    main()
