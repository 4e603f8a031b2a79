"""Demo (paper 001 Fig. 5): one iiwa joint under random actions, with its safe acceleration range.

``python -m mjx_pathtrack.evaluation.limits_demo --out safe_range_demo.png [--dt 0.05] [--steps 100] [--joint 0]``
writes a PNG with position, velocity, acceleration and jerk of the joint (limits dashed) and the
safe acceleration range at each decision step.
"""

from __future__ import annotations

import argparse
import os
import tempfile

import numpy as np

def rollout(dt: float, steps: int, seed: int):
    """Random-action rollout of the iiwa; returns dense time series and the per-step ranges."""
    import jax
    import jax.numpy as jnp

    from mjx_pathtrack.robots import iiwa
    from mjx_pathtrack.core import limits as L

    lim = iiwa.joint_limits(dt)
    rng = np.random.default_rng(seed)
    p = jnp.asarray(rng.uniform(-0.5, 0.5, 7) * iiwa.POS, jnp.float32)
    v = a = jnp.zeros(7)
    fn = jax.jit(lambda p, v, a: L.safe_acceleration_range(lim, p, v, a, dt))
    sub = np.linspace(0.0, dt, 11)[:-1, None]
    dense, ranges = [], []
    for _ in range(steps):
        a_min, a_max = fn(p, v, a)
        a1 = L.action_to_acceleration(jnp.asarray(rng.uniform(-1, 1, 7), jnp.float32), a_min, a_max)
        ps, vs, accs = (np.asarray(x) for x in L.integrate(p, v, a, a1, dt, sub))
        dense.append(np.stack([ps, vs, accs, np.broadcast_to(np.asarray((a1 - a) / dt), ps.shape)], -1))
        ranges.append(np.stack([np.asarray(a_min), np.asarray(a_max)], -1))
        p, v, _ = L.integrate(p, v, a, a1, dt, dt)
        a = a1
    return np.concatenate(dense), np.array(ranges), lim


def plot(out: str, dt: float = 0.05, steps: int = 100, joint: int = 0, seed: int = 0) -> str:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    dense, ranges, lim = rollout(dt, steps, seed)
    t = np.arange(dense.shape[0]) * dt / 10
    limits = [float(lim.pos_max[joint]), float(lim.vel[joint]), float(lim.acc[joint]), float(lim.jerk[joint])]
    names = ["position [rad]", "velocity [rad/s]", "acceleration [rad/s²]", "jerk [rad/s³]"]
    fig, axes = plt.subplots(4, 1, figsize=(8, 9), sharex=True)
    for i, ax in enumerate(axes):
        ax.plot(t, dense[:, joint, i], lw=1.2)
        ax.axhline(limits[i], ls="--", c="k", lw=0.8)
        ax.axhline(-limits[i], ls="--", c="k", lw=0.8)
        ax.set_ylabel(names[i])
    td = (np.arange(steps) + 1) * dt
    axes[2].vlines(td, ranges[:, joint, 0], ranges[:, joint, 1], colors="tab:red", lw=2, alpha=0.6,
                   label="safe range for the next step")
    axes[2].legend(loc="upper right", fontsize=8)
    axes[-1].set_xlabel("time [s]")
    fig.suptitle(f"iiwa joint {joint + 1}, random actions, Δt = {dt} s")
    fig.tight_layout()
    directory = os.path.dirname(os.path.abspath(out))
    with tempfile.NamedTemporaryFile(dir=directory, suffix=".png", delete=False) as tmp:
        fig.savefig(tmp.name, dpi=110)
    os.replace(tmp.name, out)
    plt.close(fig)
    return out


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--out", default="safe_range_demo.png")
    parser.add_argument("--dt", type=float, default=0.05)
    parser.add_argument("--steps", type=int, default=100)
    parser.add_argument("--joint", type=int, default=0, choices=range(7))
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args(argv)
    print("wrote", plot(args.out, args.dt, args.steps, args.joint, args.seed))


if __name__ == "__main__":
    main()
