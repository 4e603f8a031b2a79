"""PNG plots of one evaluated episode: commanded joint p/v/a/jerk with their limits, and the
reference vs the executed path in joint space and in Cartesian space (written atomically)."""

from __future__ import annotations

import io
from pathlib import Path as FsPath

import jax
import jax.numpy as jnp
import numpy as np

from mjx_pathtrack.evaluation import rollout as E
from mjx_pathtrack.envs.tracking import PathTrackingEnv
from mjx_pathtrack.fileio import atomic_write_bytes


def commanded_profile(env: PathTrackingEnv, ro: E.Rollout, b: int, per_step: int = 12) -> dict[str, np.ndarray]:
    """Time ``[K]`` [s] and commanded p, v, a, jerk ``[K, n]`` of episode ``b`` at ``per_step``
    instants per decision step (exact constant-jerk evaluation)."""
    dt = env.config.dt
    live = np.flatnonzero(ro.live[:, b])
    n = ro.p0.shape[-1]
    p0 = np.concatenate([ro.p0[b][None], ro.p[live[:-1], b]]) if len(live) else np.zeros((0, n))
    v0 = np.concatenate([np.zeros((1, n)), ro.v[live[:-1], b]]) if len(live) else p0
    a0 = np.concatenate([np.zeros((1, n)), ro.a[live[:-1], b]]) if len(live) else p0
    a1 = ro.a[live, b]
    tau = dt * np.arange(per_step) / per_step
    j = (a1 - a0) / dt
    t = tau[None, :, None]
    p = p0[:, None] + t * (v0[:, None] + t * (0.5 * a0[:, None] + t * j[:, None] / 6.0))
    v = v0[:, None] + t * (a0[:, None] + 0.5 * t * j[:, None])
    a = a0[:, None] + t * j[:, None]
    time = (np.arange(len(live))[:, None] * dt + tau[None]).reshape(-1)
    flat = lambda x: x.reshape(-1, n)  # noqa: E731
    return {"t": time, "p": flat(p), "v": flat(v), "a": flat(a), "jerk": flat(np.broadcast_to(j[:, None], p.shape))}


def _save(fig, file: FsPath) -> FsPath:
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=110)
    atomic_write_bytes(file, buf.getvalue())
    return file


def plot_episode(out_dir: FsPath, env: PathTrackingEnv, ro: E.Rollout, robot=None, b: int = 0) -> list[FsPath]:
    """Write ``episode{b}_kinematics.png``, ``episode{b}_joint_path.png`` and (with ``robot``)
    ``episode{b}_cartesian.png`` under ``out_dir``; returns the files."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    lim = env.limits
    files = []
    prof = commanded_profile(env, ro, b)
    lo, hi = np.asarray(lim.pos_min), np.asarray(lim.pos_max)
    finite = np.isfinite(lo) & np.isfinite(hi)
    pos = np.where(finite, (2 * prof["p"] - np.where(finite, lo + hi, 0)) / np.where(finite, hi - lo, 1), np.nan)
    fig, axes = plt.subplots(4, 1, figsize=(9, 10), sharex=True)
    for ax, (label, y) in zip(axes, (("position", pos), ("velocity", prof["v"] / np.asarray(lim.vel)),
                                      ("acceleration", prof["a"] / np.asarray(lim.acc)),
                                      ("jerk", prof["jerk"] / np.asarray(lim.jerk)))):
        ax.plot(prof["t"], y, lw=1)
        for level in (-1, 1):
            ax.axhline(level, color="k", ls="--", lw=0.8)
        ax.set_ylabel(f"{label} / limit")
        ax.set_ylim(-1.15, 1.15)
    axes[0].legend([f"joint {j + 1}" for j in range(lim.n_joints)], ncol=min(lim.n_joints, 7), fontsize=7,
                   loc="upper right")
    axes[-1].set_xlabel("time [s]")
    axes[0].set_title(f"episode {b} (path {int(ro.path_index[b])}): commanded motion, limits dashed")
    fig.tight_layout()
    files.append(_save(fig, out_dir / f"episode{b}_kinematics.png"))
    plt.close(fig)

    pj = np.asarray(env.path_joints)
    offsets, executed = E.sample_executed(E.executed_polyline(ro, b), pj)
    path = jax.tree.map(lambda x: x[b:b + 1], ro.paths)
    ref = np.asarray(E.reference_points(path, jnp.asarray(ro.s_start[b] + offsets[None], jnp.float32)))[0]
    fig, ax = plt.subplots(figsize=(9, 5))
    for k, j in enumerate(pj):
        line, = ax.plot(offsets, ref[:, k], lw=2, alpha=0.4)
        ax.plot(offsets, executed[:, j], lw=1, ls="--", color=line.get_color())
    ax.set_xlabel("arc length from the episode start [rad]")
    ax.set_ylabel("joint position [rad]")
    ax.set_title("reference (thick) vs executed (dashed) at equal arc length")
    fig.tight_layout()
    files.append(_save(fig, out_dir / f"episode{b}_joint_path.png"))
    plt.close(fig)

    if robot is not None:
        full_ref = np.broadcast_to(np.asarray(env.home), executed.shape).copy()
        full_ref[:, pj] = ref
        x_ref = np.asarray(robot.fk(jnp.asarray(full_ref, jnp.float32))[0])[:, 0]
        x_exe = np.asarray(robot.fk(jnp.asarray(executed, jnp.float32))[0])[:, 0]
        fig = plt.figure(figsize=(7, 6))
        ax = fig.add_subplot(projection="3d")
        ax.plot(*x_ref.T, lw=3, alpha=0.4, label="reference")
        ax.plot(*x_exe.T, lw=1, ls="--", label="executed")
        ax.scatter(*x_exe[0], marker="o", label="start")
        ax.set_xlabel("x [m]"), ax.set_ylabel("y [m]"), ax.set_zlabel("z [m]")
        ax.set_title(f"target point {robot.target_sites[0]}")
        ax.legend()
        files.append(_save(fig, out_dir / f"episode{b}_cartesian.png"))
        plt.close(fig)
    return files
