"""Episode metrics of a policy on a path-tracking environment (paper 000 §IV, docs/method.md §6).

:func:`evaluate` runs a batch of episodes to their end (no auto-reset), jitted and vmapped, and
returns per-episode arrays; :func:`summarize` turns them into the numbers training reports.

The full evaluation (``evaluate.py``): :func:`rollout` runs one episode per chosen path and
records every step inside the jitted scan (executed sub-step positions, commanded states,
observations, in-step limit ratios); :func:`episode_table` post-processes it in NumPy into the
paper's per-episode metrics (durations, whole-path joint and Cartesian deviations sampled every
0.01 rad of arc length, terminations, limit audit); :func:`aggregate` gives means/maxima;
:func:`decision_times` measures the computation time per decision (Table IX).
"""

from __future__ import annotations

from typing import Any, Callable, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from mjx_pathtrack.core import limits as L
from mjx_pathtrack.core import spline as S
from mjx_pathtrack.envs import episodes
from mjx_pathtrack.envs.tracking import PathTrackingEnv
from mjx_pathtrack.evaluation.geometry import SAMPLE_SPACING, polyline_distance, rotation_angle, sample_executed  # noqa: F401  (re-exported)

Array = jax.Array
Policy = episodes.Policy


class EpisodeMetrics(NamedTuple):
    """Per-episode results ``[B]``: return; steps until done; time [s] when the path end was
    first reached and when the robot had stopped (``nan`` if never); mean over steps of d_mean
    and max of d_max [rad]; success (stopped / timed out with the last point within the success
    deviation of the end knot); terminated on deviation; final arc progress in [0, 1]; ended as
    a task failure (the env's ``task_failed``, e.g. the humanoid fell; 0 for plain tracking)."""

    episode_return: Array
    steps: Array
    end_time: Array
    stop_time: Array
    mean_deviation: Array
    max_deviation: Array
    success: Array
    terminated_deviation: Array
    progress: Array
    task_failed: Array


def reset_episodes(env: PathTrackingEnv, rng: Array, n_episodes: int, path_indices: Array | None = None):
    """``(state [B], steps_key)``: the resets of the episodes :func:`evaluate` (``path_indices``
    None: random paths) and :func:`rollout` (int ``[B]`` dataset paths) run for ``rng``, and the key
    their steps' keys are split from."""
    reset_keys = jax.random.split(rng, n_episodes + 1)
    args = (reset_keys[1:],) if path_indices is None else (reset_keys[1:], path_indices)
    return jax.vmap(env.reset)(*args), reset_keys[0]


def evaluate(env: PathTrackingEnv, policy: Policy, rng: Array, n_episodes: int,
             max_steps: int | None = None) -> EpisodeMetrics:
    """Run ``n_episodes`` episodes (reset keys split from ``rng``) until done or ``max_steps``
    (default: the config's longest episode); metrics after ``done`` are frozen."""
    max_steps = env.config.max_episode_steps() + 1 if max_steps is None else max_steps
    state, steps_key = reset_episodes(env, rng, n_episodes)
    metrics, _, _ = run_episodes(env, policy, state, jax.random.split(steps_key, max_steps), record=False)
    return metrics


def episode_references(env: PathTrackingEnv, rng: Array, n_episodes: int):
    """``(paths [B], s_start [B])``: the reference (truncated to the sub-path) and start arc
    position [rad] of the episodes :func:`evaluate` runs for ``rng`` (for their baselines)."""
    reset_keys = jax.random.split(rng, n_episodes + 1)
    track = jax.vmap(env.initial_state)(reset_keys[1:])
    return jax.vmap(env.path)(track.path_index, track.n_knots), np.asarray(track.s_start)


class EpisodeAccumulator(NamedTuple):
    """Running per-episode values ``[B]`` of :func:`run_episodes` (see :class:`EpisodeMetrics`)."""

    episode_return: Array
    end_time: Array
    stop_time: Array
    deviation_sum: Array
    max_deviation: Array
    success: Array
    terminated_deviation: Array
    progress: Array
    task_failed: Array


def run_episodes(env: PathTrackingEnv, policy: Policy, state, keys: Array, record: bool = False):
    """Scan the batch ``state`` ``[B]`` over ``len(keys)`` steps with the package's rollout engine
    (:func:`mjx_pathtrack.envs.episodes.run_episodes`). Returns ``(EpisodeMetrics, done [B],
    records)``; ``records`` (``record=True``) is a dict of time-major arrays (see :class:`Rollout`)."""
    dt = env.config.dt
    zeros = jnp.zeros(state.obs.shape[0])
    nan = jnp.full_like(zeros, jnp.nan)

    def accumulate(acc: EpisodeAccumulator, before, after, live, steps) -> EpisodeAccumulator:
        m = after.metrics
        t = (steps + 1) * dt
        reached = live & (m["reached_end"] > 0)
        now_done = live & (after.done > 0)
        stopped = now_done & (m["reached_end"] > 0) & (m["terminated_deviation"] == 0)
        return EpisodeAccumulator(
            acc.episode_return + jnp.where(live, after.reward, 0.0),
            jnp.where(reached & jnp.isnan(acc.end_time), t, acc.end_time),
            jnp.where(stopped & jnp.isnan(acc.stop_time), t, acc.stop_time),
            acc.deviation_sum + jnp.where(live, m["d_mean"], 0.0),
            jnp.where(live, jnp.maximum(acc.max_deviation, m["d_max"]), acc.max_deviation),
            jnp.where(now_done, m["success"], acc.success),
            jnp.where(now_done, m["terminated_deviation"], acc.terminated_deviation),
            jnp.where(live, m["progress"], acc.progress),
            jnp.where(now_done, m.get("task_failed", zeros), acc.task_failed))

    def step_record(before, after, live):
        record = _step_record(env, before.pipeline_state, after.pipeline_state, before.obs, live)
        return {**record, "progress": after.metrics["progress"], "deviation": after.metrics["d_max"]}

    init = EpisodeAccumulator(zeros, nan, nan, zeros, zeros, zeros, zeros, zeros, zeros)
    final, records = episodes.run_episodes(jax.vmap(env.step), policy, state, keys, accumulate, init,
                                           step_record if record else None)
    a, steps = final.acc, final.steps
    metrics = EpisodeMetrics(a.episode_return, steps, a.end_time, a.stop_time, a.deviation_sum / jnp.maximum(steps, 1),
                             a.max_deviation, a.success, a.terminated_deviation, a.progress, a.task_failed)
    return metrics, final.done, records


def _step_record(env: PathTrackingEnv, before, after, obs: Array, live: Array) -> dict[str, Array]:
    """What one step leaves for the NumPy post-processing (batch ``[B]``): the executed positions
    at the sub-steps ``[B, S+1, n]`` (start included), the commanded state after the step, the
    observation the decision saw, ``live`` and the in-step limit ratios ``[B, 4, n]``."""
    dt = env.config.dt
    _, q, _ = jax.vmap(lambda e, p, v, a0, a1: env.executor.execute(e, p, v, a0, a1, dt))(
        before.executor, before.p, before.v, before.a, after.a)
    scene = jax.vmap(env.executor.scene)(after.executor) if hasattr(env.executor, "scene") else {}
    return {"executed": q, "p": after.p, "v": after.v, "a": after.a, "obs": obs, "live": live,
            "limit_ratio": limit_ratios(env.limits, before.p, before.v, before.a, after.a, dt), "scene": scene}


def limit_ratios(lim: L.JointLimits, p: Array, v: Array, a0: Array, a1: Array, dt: float) -> Array:
    """``[..., 4, n]``: exact maxima over one constant-jerk step of |position|, |velocity|,
    |acceleration| and |jerk| normalised by the limits (position mapped to [-1, 1] over
    ``[pos_min, pos_max]``; 0 for continuous joints). A value > 1 is a violation."""
    ext = L.step_extrema(p, v, a0, a1, dt)
    finite = jnp.isfinite(lim.pos_min) & jnp.isfinite(lim.pos_max)
    mid = jnp.where(finite, 0.5 * (lim.pos_min + lim.pos_max), 0.0)
    half = jnp.where(finite, 0.5 * (lim.pos_max - lim.pos_min), 1.0)
    pos = jnp.where(finite, jnp.maximum(jnp.abs(ext.p_max - mid), jnp.abs(ext.p_min - mid)) / half, 0.0)
    vel = jnp.maximum(jnp.abs(ext.v_max), jnp.abs(ext.v_min)) / lim.vel
    return jnp.stack([pos, vel, ext.a_abs / lim.acc, ext.jerk_abs / lim.jerk], axis=-2)


def summarize(m: EpisodeMetrics, baseline: np.ndarray | None = None) -> dict[str, float]:
    """Means over episodes: return, end-reached rate, success rate, mean stop time [s] (of the
    episodes that stopped), mean/max joint deviation [rad], deviation terminations; with the
    baseline durations ``[B]`` [s] of the same episodes (TOPP-RA), also the mean ratio of the
    stop time to it (``ratio_to_toppra``, over the episodes that stopped)."""
    m = jax.tree.map(np.asarray, m)
    stopped = ~np.isnan(m.stop_time)
    extra = {}
    if baseline is not None:
        ok = stopped & np.isfinite(baseline) & (baseline > 0)
        extra["ratio_to_toppra"] = float(np.mean(m.stop_time[ok] / baseline[ok])) if ok.any() else float("nan")
    return {
        "return": float(m.episode_return.mean()),
        "end_reached": float((~np.isnan(m.end_time)).mean()),
        "success": float(m.success.mean()),
        "stop_time_s": float(m.stop_time[stopped].mean()) if stopped.any() else float("nan"),
        "mean_deviation": float(m.mean_deviation.mean()),
        "max_deviation": float(m.max_deviation.mean()),
        "terminated_deviation": float(m.terminated_deviation.mean()),
        "progress": float(m.progress.mean()),
        "task_failed": float(m.task_failed.mean()),
        **extra,
    }


def brax_policy(make_inference_fn, params, deterministic: bool = True) -> Policy:
    """A :data:`Policy` from Brax PPO's ``make_inference_fn`` and trained ``params``."""
    inference = make_inference_fn(params, deterministic=deterministic)
    return lambda obs, key: inference(obs, key)[0]


def make_evaluator(env: PathTrackingEnv, make_inference_fn, n_episodes: int, max_steps: int | None = None,
                   deterministic: bool | None = True) -> Callable[..., EpisodeMetrics]:
    """``evaluator(params, rng) -> EpisodeMetrics``, jitted once (params are an argument, so
    evaluating new parameters during training does not recompile). ``deterministic=None``:
    ``evaluator(params, rng, sampled)`` with a bool ``sampled`` that picks sampled actions
    instead of the mean, both from one compiled program."""
    if deterministic is not None:
        @jax.jit
        def evaluator(params, rng):
            return evaluate(env, brax_policy(make_inference_fn, params, deterministic), rng, n_episodes, max_steps)

        return evaluator

    @jax.jit
    def either(params, rng, sampled):
        mean, draw = brax_policy(make_inference_fn, params, True), brax_policy(make_inference_fn, params, False)
        return evaluate(env, lambda obs, key: jnp.where(sampled, draw(obs, key), mean(obs, key)), rng, n_episodes,
                        max_steps)

    return either


# ---------------------------------------------------------------------------------------------
# Full evaluation (paper 000 §IV, docs/method.md §6): recorded rollout + NumPy post-processing
# ---------------------------------------------------------------------------------------------

#: tolerance of the limit audit (normalised units)
AUDIT_TOLERANCE = 1e-6
TERMINATION_REASONS = ("stopped_at_end", "deviation", "task_failed", "time_budget", "not_done")


class Rollout(NamedTuple):
    """A recorded batch of ``B`` episodes over ``T`` steps (NumPy arrays, time-major).

    executed ``[T, B, S+1, n]`` executed joint positions at the sub-steps of each step (start
    included) [rad]; p, v, a ``[T, B, n]`` commanded state after each step; obs ``[T, B, obs]``
    the observation each decision saw; live ``[T, B]`` bool: the step belongs to the episode;
    limit_ratio ``[T, B, 4, n]`` in-step maxima of |p|, |v|, |a|, |jerk| / limits; p0 ``[B, n]``
    start state (at rest); paths: the episodes' reference :class:`~mjx_pathtrack.core.spline.Path`
    batch ``[B]``; s_start ``[B]`` [rad]; path_index ``[B]``; done ``[B]`` bool; metrics: the
    :class:`EpisodeMetrics` of the same run; progress, deviation ``[T, B]``: the path progress
    (fraction) and the step's largest weighted deviation [rad] after each step; scene: what the
    executor keeps of the scene after each step (``executor.scene``: ``"qpos"`` ``[T, B, nq]`` of
    an MJX robot, ``"ball"`` ``[T, B, 3]`` in the plate frame [m]; empty for the kinematic one),
    for rendering (:mod:`mjx_pathtrack.evaluation.video`).
    """

    executed: np.ndarray
    p: np.ndarray
    v: np.ndarray
    a: np.ndarray
    obs: np.ndarray
    live: np.ndarray
    limit_ratio: np.ndarray
    p0: np.ndarray
    paths: Any
    s_start: np.ndarray
    path_index: np.ndarray
    done: np.ndarray
    metrics: EpisodeMetrics
    progress: np.ndarray
    deviation: np.ndarray
    scene: dict


def rollout(env: PathTrackingEnv, policy: Policy, rng: Array, path_indices, max_steps: int | None = None) -> Rollout:
    """Run one episode per entry of ``path_indices`` (int ``[B]``: dataset paths; sub-paths are
    drawn from keys split from ``rng``, so a fixed ``rng`` gives fixed sub-paths), batched and
    jitted, recording every step (:class:`Rollout`)."""
    indices = jnp.asarray(np.asarray(path_indices), jnp.int32)
    n = int(indices.shape[0])
    max_steps = env.config.max_episode_steps() + 1 if max_steps is None else int(max_steps)

    @jax.jit
    def run(rng, indices):
        state, steps_key = reset_episodes(env, rng, n, indices)
        metrics, done, records = run_episodes(env, policy, state, jax.random.split(steps_key, max_steps), record=True)
        track = state.pipeline_state
        paths = jax.vmap(env.episode_path)(track)
        return metrics, done, records, track.p, track.s_start, paths

    metrics, done, rec, p0, s_start, paths = jax.tree.map(np.asarray, run(rng, indices))
    return Rollout(rec["executed"], rec["p"], rec["v"], rec["a"], rec["obs"], rec["live"], rec["limit_ratio"], p0,
                   paths, s_start, np.asarray(indices), done, metrics, rec["progress"], rec["deviation"], rec["scene"])


def executed_polyline(ro: Rollout, b: int) -> np.ndarray:
    """Executed positions ``[P, n]`` of episode ``b`` at every sub-step, start point first."""
    q = ro.executed[ro.live[:, b], b]  # [L, S+1, n]
    if q.shape[0] == 0:
        return ro.p0[b][None]
    return np.concatenate([q[0, :1], q[:, 1:].reshape(-1, q.shape[-1])])


def _pad(rows: list[np.ndarray], fill: float) -> tuple[np.ndarray, np.ndarray]:
    width = max(len(r) for r in rows)
    out = np.full((len(rows), width) + rows[0].shape[1:], fill, np.float64)
    mask = np.zeros((len(rows), width), bool)
    for i, r in enumerate(rows):
        out[i, :len(r)], mask[i, :len(r)] = r, True
    return out, mask


@jax.jit
def reference_points(paths: S.Path, s: Array) -> Array:
    """Reference positions ``[B, M, m]`` of a stacked path batch ``[B]`` at arc lengths ``s [B, M]``
    (clamped to each path's end)."""
    return jax.vmap(S.point_at)(paths, s)


def episode_table(env: PathTrackingEnv, ro: Rollout, robot=None, spacing: float = SAMPLE_SPACING,
                  fk_chunk: int = 8192, measure: list | None = None) -> dict[str, np.ndarray]:
    """Per-episode metrics ``{name: [B]}`` of a :class:`Rollout` (docs/method.md §6).

    Durations [s] (``stop_time_s``: robot stopped after reaching the end, ``end_time_s``: end first
    reached; NaN if never); joint deviation [rad] mean/max/final over the whole executed path
    sampled every ``spacing`` rad of arc length against the reference at equal arc length from the
    episode start (unweighted L2 over the path joints); with ``robot`` (a
    :class:`~mjx_pathtrack.robots.registry.Robot`) the Cartesian position [cm] and orientation [deg]
    deviations of the target points (mean over target points per sample) and the Cartesian contour
    deviation [cm] (:func:`contour_deviation`: distance from the reference's Cartesian curve,
    whatever the arc position); end reached, success,
    termination reason; limit audit ``max_{pos,vel,acc,jerk}_ratio``.

    ``measure``: per dataset path a :class:`~mjx_pathtrack.core.spline_fit.SplineFit`, the curve
    the deviations are measured against instead of the environment's reference (a user's own
    curve, which the policy tracks re-knotted: :mod:`mjx_pathtrack.paths.user_paths`); arc
    positions on the reference map onto it in proportion to the two curves' lengths.
    """
    pj = np.asarray(env.path_joints)
    m = ro.metrics
    B = len(ro.s_start)
    offsets, samples = zip(*(sample_executed(executed_polyline(ro, b), pj, spacing) for b in range(B)))
    off, mask = _pad(list(offsets), 0.0)
    exe, _ = _pad(list(samples), 0.0)
    if measure is None:
        ref = np.asarray(reference_points(ro.paths, jnp.asarray(ro.s_start[:, None] + off, jnp.float32)), np.float64)
    else:
        ref = measured_points(env, ro, measure, off, start_offset=True)
    dev = np.linalg.norm(ref - exe[..., pj], axis=-1)
    last = mask.sum(1) - 1
    out: dict[str, np.ndarray] = {
        "path_index": ro.path_index.astype(np.int64),
        "steps": m.steps.astype(np.int64),
        "stop_time_s": m.stop_time, "end_time_s": m.end_time,
        "end_reached": ~np.isnan(m.end_time), "success": m.success > 0,
        "progress": m.progress, "return": m.episode_return,
        "joint_dev_mean": np.where(mask, dev, 0.0).sum(1) / mask.sum(1),
        "joint_dev_max": np.where(mask, dev, -np.inf).max(1),
        "joint_dev_final": dev[np.arange(B), last],
        "n_samples": mask.sum(1),
    }
    if robot is not None:
        ref_full = exe.copy()
        ref_full[..., :] = np.asarray(env.home)
        ref_full[..., pj] = ref
        curves, counts = reference_curves(env, ro, spacing, measure)
        k = int(mask.sum())  # valid samples; FK of the reference there, the executed ones, the curves
        pos, rot = _fk_chunked(robot, np.concatenate([ref_full[mask], exe[mask], curves.reshape(-1, curves.shape[-1])]),
                               fk_chunk)
        pos_dev = np.linalg.norm(pos[:k] - pos[k:2 * k], axis=-1).mean(-1)
        rot_dev = rotation_angle(rot[:k], rot[k:2 * k]).mean(-1)
        curve_points = pos[2 * k:].reshape(*curves.shape[:2], *pos.shape[1:])  # [B, W, T, 3]
        contour = contour_deviation(pos[k:2 * k], np.nonzero(mask)[0], curve_points, counts)
        for name, values, scale in (("cart_pos_dev_cm", pos_dev, 100.0), ("cart_rot_dev_deg", rot_dev, 180 / np.pi),
                                    ("cart_contour_dev_cm", contour, 100.0)):
            full = np.zeros(mask.shape)
            full[mask] = values * scale
            out[f"{name}_mean"] = full.sum(1) / mask.sum(1)
            out[f"{name}_max"] = np.where(mask, full, -np.inf).max(1)
            out[f"{name}_final"] = full[np.arange(B), last]
    reason = np.where(~ro.done, "not_done", np.where(m.task_failed > 0, "task_failed",
                      np.where(m.terminated_deviation > 0, "deviation",
                               np.where(~np.isnan(m.stop_time), "stopped_at_end", "time_budget"))))
    out["termination"] = reason
    out["task_failed"] = m.task_failed > 0
    ratios = np.where(ro.live[..., None, None], ro.limit_ratio, 0.0).max(axis=(0, 3))  # [B, 4]
    for i, q in enumerate(("pos", "vel", "acc", "jerk")):
        out[f"max_{q}_ratio"] = ratios[:, i]
    return out


def measured_points(env: PathTrackingEnv, ro: Rollout, measure: list, s: np.ndarray,
                    start_offset: bool) -> np.ndarray:
    """Points ``[B, M, m]`` of the curves ``measure`` (one fit per dataset path) for the episodes
    of ``ro`` at arc positions ``s [B, M]`` given on the episode's reference (from its start if
    ``start_offset``, else absolute), mapped in proportion to the lengths of the reference and the
    measured curve, clamped to the sub-path's end (float64)."""
    full = np.asarray(env.paths.length, np.float64)[ro.path_index]
    sub_end = np.asarray(ro.paths.length, np.float64)
    out = np.empty(s.shape + (len(env.path_joints),))
    for b, index in enumerate(ro.path_index):
        fit = measure[int(index)]
        scale = fit.length / max(full[b], 1e-12)
        start = scale * ro.s_start[b] if start_offset else 0.0
        end = scale * sub_end[b]
        out[b] = fit.point_at(np.clip(start + (s[b] if start_offset else scale * s[b]), 0.0, end))
    return out


def reference_curves(env: PathTrackingEnv, ro: Rollout, spacing: float = SAMPLE_SPACING, measure: list | None = None
                     ) -> tuple[np.ndarray, np.ndarray]:
    """Each episode's reference from its start ``s_start`` to its end, sampled every ``spacing``
    rad of arc length, both ends included, as full joint configurations (the joints off the path
    at ``env.home``): ``(curves [B, W, n], counts [B])``, episode ``b``'s samples being
    ``curves[b, :counts[b]]`` (the rest repeat its end). ``measure``: the curves to sample instead
    of the references (:func:`measured_points`)."""
    pj = np.asarray(env.path_joints)
    s0 = np.asarray(ro.s_start, np.float64)
    end = np.maximum(np.asarray(ro.paths.length, np.float64), s0)
    counts = np.floor((end - s0) / spacing + 1e-9).astype(int) + 2
    k = np.arange(int(counts.max()))[None]
    s = np.where(k >= counts[:, None] - 1, end[:, None], np.minimum(s0[:, None] + spacing * k, end[:, None]))
    if measure is None:
        ref = np.asarray(reference_points(ro.paths, jnp.asarray(s, jnp.float32)), np.float64)
    else:
        ref = measured_points(env, ro, measure, s, start_offset=False)
    curves = np.broadcast_to(np.asarray(env.home, np.float64), ref.shape[:2] + (len(env.home),)).copy()
    curves[..., pj] = ref
    return curves, counts


def contour_deviation(points: np.ndarray, episode: np.ndarray, curves: np.ndarray, counts: np.ndarray) -> np.ndarray:
    """Contour deviation [m] of executed target points ``points [K, T, 3]`` of episodes
    ``episode [K]``: each target point's distance from its reference curve (the polyline
    ``curves[b, :counts[b], t]`` of :func:`reference_curves`' FK, ``[B, W, T, 3]``), mean over the
    ``T`` target points. Unlike the paper's deviation at equal arc length, it does not count how
    far along the path the robot is, only how far off the path; the gap between the two is the
    arc-length drift (the executed path being longer or shorter than the reference)."""
    out = np.empty(len(points))
    for b in np.unique(episode):
        sel = episode == b
        out[sel] = np.mean([polyline_distance(points[sel, t], curves[b, :counts[b], t])
                            for t in range(points.shape[1])], axis=0)
    return out


def _fk_chunked(robot, q: np.ndarray, chunk: int) -> tuple[np.ndarray, np.ndarray]:
    """Target-point positions ``[K, T, 3]`` [m] and rotations ``[K, T, 3, 3]`` of configurations
    ``q [K, n]`` (float64 out; jitted FK in chunks of a fixed size, so that one compile serves
    every evaluation)."""
    fk = jax.jit(robot.fk)
    q = q.astype(np.float32)
    pos, rot = [], []
    for i in range(0, len(q), chunk):
        part = q[i:i + chunk]
        padded = np.concatenate([part, np.repeat(part[-1:], chunk - len(part), 0)])
        x, r = fk(jnp.asarray(padded))
        pos.append(np.asarray(x)[:len(part)])
        rot.append(np.asarray(r)[:len(part)])
    return np.concatenate(pos).astype(np.float64), np.concatenate(rot).astype(np.float64)


def aggregate(table: dict[str, np.ndarray]) -> dict[str, Any]:
    """Means over episodes (and maxima where the paper has them) of :func:`episode_table`;
    duration means count only the episodes that reached the end / stopped."""
    out: dict[str, Any] = {"episodes": int(len(table["steps"]))}
    for key in ("stop_time_s", "end_time_s"):
        valid = ~np.isnan(table[key])
        out[f"{key}_mean"] = float(table[key][valid].mean()) if valid.any() else float("nan")
        out[f"{key}_max"] = float(table[key][valid].max()) if valid.any() else float("nan")
    out["end_reached_rate"] = float(table["end_reached"].mean())
    out["success_rate"] = float(table["success"].mean())
    out["progress_mean"] = float(table["progress"].mean())
    if "task_failed" in table:
        out["task_failed_rate"] = float(np.mean(table["task_failed"]))
    for key in [k for k in table if k.endswith(("_mean", "_final")) and "dev" in k]:
        out[key] = float(table[key].mean())
    for key in [k for k in table if k.endswith("_max") and "dev" in k]:
        out[f"{key}_mean"] = float(table[key].mean())
        out[key] = float(table[key].max())
    out["termination"] = {r: float(np.mean(table["termination"] == r)) for r in TERMINATION_REASONS}
    audit = {q: float(table[f"max_{q}_ratio"].max()) for q in ("pos", "vel", "acc", "jerk")}
    out["limit_audit"] = {**audit, "ok": bool(max(audit.values()) <= 1.0 + AUDIT_TOLERANCE)}
    return out


def decision_times(env: PathTrackingEnv, policy: Policy, ro: Rollout, max_decisions: int = 200,
                   seed: int = 0) -> np.ndarray:
    """Wall times [s] of single-environment decisions (policy + safe acceleration range +
    integration to the next decision instant), jitted and compiled beforehand, on up to
    ``max_decisions`` recorded states of ``ro`` (paper 000 Table IX divides them by Δt)."""
    import time

    lim, dt = env.limits, env.config.dt

    @jax.jit
    def decide(obs, p, v, a, key):
        action = policy(obs[None], key)[0]
        a_min, a_max = L.safe_acceleration_range(lim, p, v, a, dt)
        return L.integrate(p, v, a, L.action_to_acceleration(action, a_min, a_max), dt, dt)

    t_idx, b_idx = np.nonzero(ro.live)
    pick = np.random.default_rng(seed).permutation(len(t_idx))[:max_decisions]
    # the state a decision at step t starts from: at rest on p0 for t = 0, else the state after step t - 1
    zeros = np.zeros_like(ro.p0[0])
    key = jax.random.PRNGKey(0)
    inputs = [tuple(jnp.asarray(x) for x in (ro.obs[t, b], ro.p0[b] if t == 0 else ro.p[t - 1, b],
                                             zeros if t == 0 else ro.v[t - 1, b], zeros if t == 0 else ro.a[t - 1, b]))
              for t, b in zip(t_idx[pick], b_idx[pick])]
    jax.block_until_ready(decide(*inputs[0], key))  # compile
    times = []
    for args in inputs:
        t0 = time.perf_counter()
        jax.block_until_ready(decide(*args, key))
        times.append(time.perf_counter() - t0)
    return np.asarray(times)
