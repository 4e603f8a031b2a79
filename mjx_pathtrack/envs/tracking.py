"""Path-tracking environment (paper 000 §III; docs/method.md), a Brax ``Env``.

One step, per environment (``jax.vmap`` over the batch; docs/architecture.md "Data flow of one step"):

1. the action in [-1, 1]^n is mapped into the safe acceleration range of the current state
   or, once the path end was reached, replaced by the fastest safe braking acceleration;
2. the acceleration goes linearly to the new value over ``dt`` (constant jerk); the executor
   (:mod:`~mjx_pathtrack.envs.executors`) turns these setpoints into the executed motion at
   ``substeps`` instants: the kinematic one follows them exactly (the papers' no-feedback
   tasks), the MJX one measures servo-controlled physics;
3. the arc length ``l`` of the executed path-joint motion advances the position ``s`` on the
   reference (no projection); the deviation ``d`` compares executed points with the reference
   at equal arc length;
4. reward ``alpha R_l + w R_d(d_max) + w R_d(d_mean) (+ R_action)``; termination on deviation,
   robot stopped at the end (its reward multiplied by the remaining steps) or the time budget.

The environment's own state is the ``pipeline_state`` (:class:`TrackState`) so that Brax's
auto-reset restores it; use :func:`mjx_pathtrack.envs.wrappers.wrap_for_training`, which draws a
*fresh* episode on every reset instead of replaying the first one.
"""

from __future__ import annotations

from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from mjx_pathtrack import _quiet  # noqa: F401,I001  (before brax / mujoco.mjx: silences their Warp notices)
from brax.envs.base import Env, State

from mjx_pathtrack.core import limits as L
from mjx_pathtrack.core import reward as R
from mjx_pathtrack.core import spline as S
from mjx_pathtrack.core.knot_rule import KnotRule
from mjx_pathtrack.envs.executors import KinematicExecutor
from mjx_pathtrack.envs.settings import (DEVIATION_SCALE, END_BRAKING, END_STOP, KNOTS_FRAMES,  # noqa: F401
                                        SPEED_RATIO_SCALE, EnvConfig)  # (re-exported)

Array = jax.Array


class TrackState(NamedTuple):
    """Per-environment state (all float32 unless noted).

    p, v, a ``[n]``: commanded joint state at the decision instant; s ``[]``: arc position on the
    reference; s_start ``[]``: where the episode started on it; path_index ``[]`` int32;
    n_knots ``[]`` int32: knots of the episode's (truncated) path; steps ``[]`` int32 taken;
    max_steps ``[]`` int32 time budget; braking ``[]`` bool; rng: key for the next reset;
    path: the episode's own :class:`~mjx_pathtrack.core.spline.Path` if the config is ``adjustable``
    (else None: the path is the dataset's ``path_index`` truncated to ``n_knots``);
    executor: the executor's state (None for the kinematic one, ``mjx.Data`` for MJX).
    """

    p: Array
    v: Array
    a: Array
    s: Array
    s_start: Array
    path_index: Array
    n_knots: Array
    steps: Array
    max_steps: Array
    braking: Array
    rng: Array
    path: S.Path | None = None
    executor: Any = None


class PathTrackingEnv(Env):
    """Follow reference paths from a dataset as fast as possible within the joint limits.

    ``limits``: :class:`~mjx_pathtrack.core.limits.JointLimits` of all ``n`` actuated joints;
    ``paths``: stacked :class:`~mjx_pathtrack.core.spline.Path` batch ``[B]`` over the path joints;
    ``max_dis_between_knots`` [rad]: the dataset's largest knot spacing (observation scale);
    ``path_joints``: indices of the joints that form the path (default: all);
    ``home`` ``[n]``: start position of joints outside the path (default 0);
    ``executor``: :mod:`~mjx_pathtrack.envs.executors` object (default: kinematic with
    ``config.substeps``), its sub-steps must match ``config.substeps``;
    ``knot_rule``: where the training paths have their knots
    (:class:`~mjx_pathtrack.core.knot_rule.KnotRule`; default the papers' curvature rule capped at
    ``max_dis_between_knots``): a user's path is re-knotted by it before the policy sees it.
    """

    def __init__(self, limits: L.JointLimits, paths: S.Path, max_dis_between_knots: float,
                 config: EnvConfig = EnvConfig(), path_joints=None, home=None, executor=None,
                 knot_rule: KnotRule | None = None):
        n = limits.n_joints
        self.limits = limits
        self.config = config
        self.paths = paths
        self.path_joints = np.arange(n) if path_joints is None else np.asarray(path_joints, np.int32)
        m = len(self.path_joints)
        if paths.knots.ndim != 3 or paths.knots.shape[-1] != m:
            raise ValueError(f"paths must be a stacked batch [B, max_knots, {m}] over the {m} path joints, "
                             f"got knots of shape {paths.knots.shape}")
        if not np.isfinite(max_dis_between_knots) or max_dis_between_knots <= 0:
            raise ValueError(f"max_dis_between_knots must be > 0, got {max_dis_between_knots}")
        if config.deviation_weights is not None and len(config.deviation_weights) != m:
            raise ValueError(f"deviation_weights has {len(config.deviation_weights)} values for {m} path joints")
        self.max_dis = float(max_dis_between_knots)
        self.knot_rule = KnotRule(max_spacing=self.max_dis) if knot_rule is None else knot_rule
        self.home = jnp.zeros(n) if home is None else jnp.asarray(home, jnp.float32)
        self.n_paths = int(paths.knots.shape[0])
        self.executor = KinematicExecutor(config.substeps) if executor is None else executor
        if self.executor.substeps != config.substeps:
            raise ValueError(f"executor has {self.executor.substeps} sub-steps per decision step, "
                             f"config.substeps is {config.substeps}")

    # -- Brax interface ---------------------------------------------------------------------

    #: task name recorded in exported policies' manifests
    task_name = "tracking"

    @property
    def observation_size(self) -> int:
        n, m, N = self.limits.n_joints, len(self.path_joints), self.config.n_next
        return 3 * n + m * (N + 1) + 2 + N + sum(size for _, size in self.tracking_extra_blocks()) + \
            sum(size for _, size in self.extra_observation_blocks())

    def tracking_extra_blocks(self) -> list[tuple[str, int]]:
        """Optional path-tracking blocks ``[(name, size), ...]`` after the papers' observation and
        before a task's: the deviation vector with ``observe_deviation``, the segments' speed
        ratios with ``observe_speed_limits``."""
        return [("deviation", len(self.path_joints))] * self.config.observe_deviation + \
            [("speed_limits", self.config.n_next)] * self.config.observe_speed_limits

    def extra_observation_blocks(self) -> list[tuple[str, int]]:
        """Named task-specific blocks ``[(name, size), ...]`` that :meth:`observe` appends after
        the path-tracking observation (none here; tasks with sensors override it)."""
        return []

    @property
    def action_size(self) -> int:
        return self.limits.n_joints

    @property
    def backend(self) -> str:
        return self.executor.name

    def reset(self, rng: Array, index: Array | None = None) -> State:
        """New episode; ``index`` (int ``[]``) picks the dataset path instead of a random one."""
        track = self.initial_state(rng, index)
        zero = jnp.zeros(())
        metrics = {k: zero for k in self.metric_names()}
        return State(pipeline_state=track, obs=self.observe(track), reward=zero, done=zero,
                     metrics=metrics, info={})

    def step(self, state: State, action: Array) -> State:
        track, reward, done, metrics = self.transition(state.pipeline_state, action)
        return state.replace(pipeline_state=track, obs=self.observe(track), reward=reward,
                             done=done.astype(jnp.float32), metrics=metrics)

    # -- episode ----------------------------------------------------------------------------

    def path(self, index: Array, n_knots: Array | None = None) -> S.Path:
        """The dataset path ``index`` (truncated to ``n_knots`` if given), copied."""
        return self.dataset_path(index, n_knots).materialize()

    def dataset_path(self, index: Array, n_knots: Array | None = None) -> S.DatasetPath:
        """The dataset path ``index`` (truncated to ``n_knots`` if given), read in place."""
        path = S.DatasetPath.of(self.paths, index)
        return path if n_knots is None else path._replace(n_knots=n_knots)

    def initial_state(self, rng: Array, index: Array | None = None) -> TrackState:
        """Random path (or dataset path ``index``), random sub-path (docs/method.md §5), robot at
        rest on its start point. The sub-path draw does not depend on ``index``."""
        cfg = self.config
        rng, k_path, k_sub = jax.random.split(rng, 3)
        if index is None:
            index = jax.random.randint(k_path, (), 0, self.n_paths)
        index = jnp.asarray(index, jnp.int32)
        full = self.dataset_path(index)
        total = full.length
        path, s0 = S.sample_sub_path(full, k_sub, cfg.start_range, cfg.min_fraction, cfg.max_fraction)
        s0 = jnp.minimum(s0, path.length)
        p = self.home.at[self.path_joints].set(S.point_at(path, s0))
        p = jnp.clip(p, self.limits.pos_min, self.limits.pos_max)
        zero = jnp.zeros_like(p)
        duration = cfg.duration * (path.length - s0) / jnp.maximum(total, 1e-9)
        trajectory_length = jnp.round(duration / cfg.dt).astype(jnp.int32) + 1
        return TrackState(p=p, v=zero, a=zero, s=s0, s_start=s0, path_index=index,
                          n_knots=path.n_knots, steps=jnp.zeros((), jnp.int32),
                          max_steps=jnp.maximum(trajectory_length - 1, 1), braking=jnp.zeros((), bool), rng=rng,
                          path=path.materialize() if cfg.adjustable else None, executor=self.executor.init(p))

    def episode_path(self, track: TrackState) -> S.Path:
        """The reference of the episode ``track`` is in (a copy of the dataset path)."""
        return track.path if track.path is not None else self.path(track.path_index, track.n_knots)

    def reference(self, track: TrackState) -> S.AnyPath:
        """The reference of the episode ``track`` is in, for the :mod:`~mjx_pathtrack.core.spline`
        functions: the dataset path read in place (:class:`~mjx_pathtrack.core.spline.DatasetPath`),
        or the episode's own path if the config is ``adjustable``."""
        return track.path if track.path is not None else self.dataset_path(track.path_index, track.n_knots)

    def replace_reference(self, state: State, new_knots: Array, n_new: Array | None = None) -> State:
        """Replace the reference ahead of the current position by a spline through ``new_knots
        [m, n_path]`` (paper 000 Fig. 4; :func:`~mjx_pathtrack.core.spline.replace_ahead`): the robot
        continues from where it is, the observation shows the new knots at once. The time budget
        is rescaled to the new remaining length; braking stops if the path now goes on.
        Needs ``EnvConfig(adjustable=True)``. Jittable; vmap it for a batch. The knots are used
        as given: re-knot a user's knots first with :meth:`user_knots` (host side), as
        :class:`~mjx_pathtrack.deploy.controller.OnlineTracker` does."""
        track = state.pipeline_state
        if track.path is None:
            raise ValueError("replace_reference needs EnvConfig(adjustable=True)")
        old = track.path
        path = S.replace_ahead(old, track.s, new_knots, n_new)
        steps_per_rad = track.max_steps / jnp.maximum(old.length - track.s_start, 1e-9)
        remaining = jnp.ceil((path.length - track.s) * steps_per_rad).astype(jnp.int32)
        track = track._replace(path=path, n_knots=path.n_knots, max_steps=track.steps + jnp.maximum(remaining, 1),
                               braking=track.braking & self.end_reached(path, track.s))
        return state.replace(pipeline_state=track, obs=self.observe(track))

    def user_knots(self, knots, start_slope=None) -> np.ndarray:
        """A user's knots ``[K, n_path]`` re-placed by the training data's :attr:`knot_rule`
        (:func:`~mjx_pathtrack.core.knot_rule.reknot`; host side, NumPy): what
        :meth:`replace_reference` should be given so that the policy sees knots like its training
        knots (``start_slope``: the unit tangent of the path being continued)."""
        from mjx_pathtrack.core.knot_rule import reknot

        return reknot(knots, self.knot_rule, start_slope)

    def transition(self, track: TrackState, action: Array, fastest_stop: Array | bool = False):
        """One decision step: ``(track, action [n]) -> (track', reward, done, metrics)``.
        ``fastest_stop`` (bool ``[]``): while braking, brake every joint as fast as it can even
        with ``end_stop="end_knot"`` (the online tracker's faults)."""
        cfg, lim = self.config, self.limits
        path = self.reference(track)
        # the safe range of the current state (computed here rather than at the end of the
        # previous step, so that a reset does not pay for it)
        a_min, a_max = L.safe_acceleration_range(lim, track.p, track.v, track.a, cfg.dt)
        a_policy = L.action_to_acceleration(action, a_min, a_max)
        a_brake = L.braking_acceleration(lim, track.p, track.v, track.a, cfg.dt, safe_range=(a_min, a_max))
        if cfg.end_stop == "end_knot":
            a_brake = jnp.where(fastest_stop, a_brake,
                                self.end_knot_acceleration(track, S.end_knot(path), a_brake, (a_min, a_max)))
        # (materialised: the executor's set-points and the integration would each recompute it)
        a_next = L.materialized(jnp.where(track.braking, a_brake, a_policy))
        # executed positions at the sub-steps of the step, start point included: [S+1, n]
        exec_state, q, sensors = self.executor.execute(track.executor, track.p, track.v, track.a, a_next, cfg.dt)
        p1, v1, _ = L.integrate(track.p, track.v, track.a, a_next, cfg.dt, cfg.dt)
        executed = q[:, self.path_joints]
        length, d = self._progress_and_deviation(path, track.s, executed)
        window = S.knot_window(path, track.s, cfg.n_next)
        s1 = jnp.minimum(track.s + length, path.length)
        d_max, d_mean = jnp.max(d), jnp.mean(d)
        # the step's acceleration change relative to the jerk limit, per joint (R_jerk; braking: none;
        # not computed at the papers' weight 0, a static value)
        jerk_ratio = (None if cfg.reward.jerk == 0 else
                      jnp.where(track.braking, 0.0, jnp.abs(a_next - track.a) / (lim.jerk * cfg.dt)))
        terms = R.tracking_terms(cfg.reward, length, window.last_s - track.s, cfg.n_next * self.max_dis,
                                 d_max, d_mean, jnp.where(track.braking, 0.0, action), window.close_to_end, jerk_ratio)
        steps = track.steps + 1
        ahead = self.stop_length(p1, v1, a_next) if cfg.end_braking == "predictive" else 0.0
        reached_end = self.end_reached(path, s1 + ahead)
        braking = track.braking | (reached_end & cfg.brake_at_end)
        new = track._replace(p=p1, v=v1, a=a_next, s=s1, executor=exec_state, steps=steps, braking=braking)
        new = self.task_update(track, new, sensors)
        task_terms, failed, task_metrics = self.task_step(track, new, sensors)
        terms = {**terms, **task_terms}
        reward = sum(terms.values())
        stopped = track.braking & jnp.all(jnp.abs(v1) < cfg.stop_velocity) & jnp.all(jnp.abs(a_next) < cfg.stop_acceleration)
        done_stop = stopped if cfg.terminate_on_stop else jnp.zeros((), bool)
        done_dev = (d_max > cfg.terminate_deviation) if cfg.terminate_deviation is not None else jnp.zeros((), bool)
        done_time = steps >= track.max_steps
        done = done_stop | done_dev | done_time | failed
        # finishing early must not lower the return: the stop reward counts for every remaining step
        reward = jnp.where(done_stop, reward * (track.max_steps + 1 - steps).astype(jnp.float32), reward)
        final_dev = R.weighted_deviation(S.end_knot(path), executed[-1], cfg.deviation_weights)
        success = done & ~done_dev & ~failed & (final_dev < cfg.success_deviation)
        metrics = {"reward": reward, **{f"reward/{k}": v for k, v in terms.items()}, "length": length, "d_max": d_max,
                   "d_mean": d_mean, "progress": (s1 - track.s_start) / jnp.maximum(path.length - track.s_start, 1e-9),
                   "reached_end": reached_end.astype(jnp.float32), "success": success.astype(jnp.float32),
                   "terminated_deviation": (done_dev & ~done_stop).astype(jnp.float32),
                   "task_failed": failed.astype(jnp.float32), **task_metrics}
        return new, reward, done, metrics

    def end_reached(self, path: S.Path, s: Array) -> Array:
        """bool ``[]``: arc position ``s`` [rad] is at the end of ``path`` (within ``end_tolerance``)."""
        return s >= path.length - self.config.end_tolerance

    def stop_length(self, p: Array, v: Array, a: Array) -> Array:
        """Path-joint arc length [rad] ``[]`` of the fastest stop from ``(p, v, a) [n]``: the
        braking accelerations (:func:`~mjx_pathtrack.core.limits.braking_acceleration`, jerk and
        acceleration limits, position limits ignored) integrated over :attr:`stop_steps`
        decision steps, as the polyline through the decision instants."""
        return self._fastest_stop(p, v, a)[1]

    def stop_position(self, p: Array, v: Array, a: Array) -> Array:
        """Joint positions ``[n]`` where the fastest stop from ``(p, v, a) [n]`` comes to rest
        (as :meth:`stop_length`)."""
        return self._fastest_stop(p, v, a)[0]

    def _fastest_stop(self, p: Array, v: Array, a: Array) -> tuple[Array, Array]:
        lim, dt, pj = self.limits, self.config.dt, self.path_joints
        free = (-lim.acc, lim.acc)

        def step(carry, _):
            p, v, a = carry
            a1 = L.braking_acceleration(lim, p, v, a, dt, safe_range=free)
            p1, v1, _ = L.integrate(p, v, a, a1, dt, dt)
            return (p1, v1, a1), jnp.linalg.norm(p1[pj] - p[pj])

        (p_end, _, _), lengths = jax.lax.scan(step, (p, v, a), None, length=self.stop_steps)
        return p_end, jnp.sum(lengths)

    def end_knot_acceleration(self, track: TrackState, end: Array, a_brake: Array,
                              safe_range: tuple[Array, Array]) -> Array:
        """Next acceleration ``[n]`` of a stop at the end knot ``end [m]`` (``end_stop="end_knot"``).

        A path joint on one side of its end-knot coordinate whose fastest stop
        (:meth:`stop_position`) would come to rest more than ``end_knot_tolerance`` short of it
        moves towards the coordinate as fast as it can while it can still stop there: the bound
        of the safe acceleration range computed with the coordinate as the position limit on its
        side (the joint's position shifted so that the coordinate lies on the real limit, which
        keeps the range's static per-joint plan). Otherwise (the stop ends within the tolerance,
        or beyond the coordinate, or the joint is off the path) it brakes (``a_brake``: the
        fastest stop, which settles; the approach alone would chatter around the coordinate on
        the decision grid), and approaches again from the other side once at rest. Everything is clipped to the state's ``safe_range``
        ``(a_min, a_max)``, so the limits hold exactly as for any other acceleration."""
        lim, dt = self.limits, self.config.dt
        target = track.p.at[self.path_joints].set(end)
        stop = self.stop_position(track.p, track.v, track.a)
        # short of the coordinate (and not beyond it): approach from below; the mirror image above
        tol = self.config.end_knot_tolerance
        up = (stop < target - tol) & (track.p <= target)
        down = (stop > target + tol) & (track.p >= target)
        shift = jnp.where(up, lim.pos_max - target, lim.pos_min - target)
        lo, hi = L.safe_acceleration_range(lim, track.p + shift, track.v, track.a, dt)
        toward = jnp.clip(jnp.where(up, hi, lo), *safe_range)
        on_path = np.zeros(lim.n_joints, bool)
        on_path[np.asarray(self.path_joints)] = True
        return jnp.where(on_path & (up | down), toward, a_brake)

    @property
    def stop_steps(self) -> int:
        """Decision steps that bound the fastest stop from any state within the limits: from
        ``|v| <= V``, ``|a| <= A`` the acceleration reaches ``-A`` within ``2 A / J`` and the
        velocity zero within ``V / A`` more (+2 steps for the grid)."""
        lim = self.limits
        worst = np.max(np.asarray(lim.vel) / np.asarray(lim.acc) + 2.0 * np.asarray(lim.acc) / np.asarray(lim.jerk))
        return int(np.ceil(worst / self.config.dt)) + 2

    #: values of :meth:`critic_features`
    CRITIC_FEATURES = ("budget_left", "path_left", "braking")

    def critic_features(self, track: TrackState) -> Array:
        """What the return depends on but the observation does not show, for a value network that
        sees more than the policy (``NetworkConfig.privileged_critic``, training only):
        ``[budget_left, path_left, braking]`` ``[3]`` float32. ``budget_left``: decision steps
        left in the time budget over :meth:`EnvConfig.max_episode_steps` [-] (the stop reward is
        multiplied by them); ``path_left``: arc length from ``s`` to the path end over ``N *
        max_dis_between_knots`` [-] (beyond the shown knots); ``braking``: 1 while braking at the end."""
        path = self.reference(track)
        horizon = float(self.config.max_episode_steps())
        return jnp.stack([(track.max_steps - track.steps).astype(jnp.float32) / horizon,
                          (path.length - track.s) / (self.config.n_next * self.max_dis),
                          track.braking.astype(jnp.float32)])

    def task_update(self, before: TrackState, after: TrackState, sensors: dict[str, Array]) -> TrackState:
        """Hook for tasks that derive state from the step (e.g. Cartesian points for their observation
        and reward), called once per step after the executor ran and before :meth:`task_step`:
        arguments as there; returns ``after`` with the task's parts updated (usually inside
        ``after.executor``). Must not change the commanded joint state (``p``, ``v``, ``a``) nor ``s``:
        the limits and the progress are the base step's. Default: ``after`` unchanged."""
        del before, sensors
        return after

    def task_step(self, before: TrackState, after: TrackState, sensors: dict[str, Array]
                  ) -> tuple[dict[str, Array], Array, dict[str, Array]]:
        """Hook for tasks with sensor feedback (:mod:`mjx_pathtrack.envs.tasks`), called once per step
        after the executor ran and :meth:`task_update`: ``before``/``after`` are the states around the
        step (``after.executor`` is the executor's new state, e.g. ``mjx.Data``), ``sensors`` what the
        executor returned.
        Returns ``(terms, failed, metrics)``: named weighted reward terms added to the step reward
        (before the robot-stop multiplication), a bool ``[]`` that ends the episode as a task failure
        (not a success; metric ``task_failed``), extra scalar metrics. A subclass that returns terms
        or metrics lists them in :meth:`metric_names`. Default: no task."""
        del before, after, sensors
        return {}, jnp.zeros((), bool), {}

    def metric_names(self) -> tuple[str, ...]:
        terms = ("distance", "max_deviation", "mean_deviation", "action", "jerk")
        return ("reward",) + tuple(f"reward/{k}" for k in terms) + ("length", "d_max", "d_mean", "progress", "reached_end",
                                                      "success", "terminated_deviation", "task_failed")

    def _progress_and_deviation(self, path: S.AnyPath, s0: Array, executed: Array) -> tuple[Array, Array]:
        """Arc length ``l`` of the executed polyline ``[S+1, m]`` and deviations ``[M]`` at
        ``M`` equally spaced arc lengths (start excluded) against the reference at ``s0 + offset``."""
        cfg = self.config
        seg = jnp.linalg.norm(jnp.diff(executed, axis=0), axis=-1)
        cum = jnp.concatenate([jnp.zeros(1), jnp.cumsum(seg)])
        length = cum[-1]
        offsets = length * jnp.arange(1, cfg.deviation_samples + 1) / cfg.deviation_samples
        i = jnp.clip(jnp.searchsorted(cum, offsets, side="left") - 1, 0, cfg.substeps - 1)
        w = jnp.clip((offsets - cum[i]) / jnp.maximum(seg[i], 1e-12), 0.0, 1.0)
        points = executed[i] + w[:, None] * (executed[i + 1] - executed[i])
        return length, S.deviation(path, s0, offsets, points, cfg.deviation_weights)

    # -- observation ------------------------------------------------------------------------

    def observe(self, track: TrackState) -> Array:
        """Observation ``[obs_size]`` in [-1, 1] (docs/method.md §4 items 1-7)."""
        cfg, lim = self.config, self.limits
        path = self.reference(track)
        window = S.knot_window(path, track.s, cfg.n_next)
        knots_lo, knots_hi = lim.pos_min[self.path_joints], lim.pos_max[self.path_joints]
        scale = cfg.n_next * self.max_dis
        if cfg.knots_frame == "relative":
            knots = (window.knots - track.p[self.path_joints]) / scale
        else:
            knots = normalize_position(window.knots, knots_lo, knots_hi)
        obs = jnp.concatenate([
            normalize_position(track.p, lim.pos_min, lim.pos_max),
            track.v / lim.vel,
            track.a / lim.acc,
            knots.reshape(-1),
            (-1.0 + 2.0 * window.offset / self.max_dis)[None],
            (-1.0 + 2.0 * window.state_length / scale)[None],
            -1.0 + 2.0 * window.knot_distances / scale,
        ])
        if cfg.observe_deviation:
            offset = (S.point_at(path, track.s) - track.p[self.path_joints]) / DEVIATION_SCALE
            obs = jnp.concatenate([obs, offset])
        if cfg.observe_speed_limits:
            pj = self.path_joints
            ratio = segment_speed_ratios(window.knots, track.v[pj], lim.vel[pj], lim.acc[pj])
            obs = jnp.concatenate([obs, -1.0 + 2.0 * ratio / SPEED_RATIO_SCALE])
        return jnp.clip(obs, -1.0, 1.0)


def segment_speed_ratios(knots: Array, v: Array, vel: Array, acc: Array) -> Array:
    """Speed ratios ``[..., N]`` [-] of the ``N`` segments between ``knots [..., N+1, m]`` [rad]:
    the speed ``|v|`` of the velocity ``v [..., m]`` [rad/s] over the fastest speed the segment
    allows, the smaller of two bounds (a sampled maximum-velocity curve, as TOPP computes it):
    along the chord, the velocity limits ``vel [m]`` [rad/s] allow ``min_i vel_i / |u_i|`` (``u``
    the chord's unit vector); on the turn at the knot that ends the segment, the acceleration
    limits ``acc [m]`` [rad/s^2] allow ``min_i sqrt(acc_i / |q''_i|)``, ``q''`` the change of unit
    chord over the mean chord length [1/rad] (at zero path acceleration). 1 means a joint would
    reach its limit moving along the segment at the current speed. A zero-length segment (beyond
    the path end) gives 0, and a turn next to one counts as none."""
    chord = jnp.diff(knots, axis=-2)
    length = jnp.linalg.norm(chord, axis=-1, keepdims=True)
    u = chord / jnp.maximum(length, 1e-12)
    # 1 / (fastest allowed speed) = max_i |u_i| / vel_i
    inverse = jnp.max(jnp.abs(u) / vel, axis=-1)
    speed = jnp.linalg.norm(v, axis=-1, keepdims=True)
    ratio_v = jnp.where(length[..., 0] > 1e-9, speed[..., 0] * inverse, 0.0)
    # curvature at the knot that ends each segment: q'' ~ (u_next - u) / mean length; the speed
    # that keeps every |q''_i| sdot^2 <= acc_i is min_i sqrt(acc_i / |q''_i|)
    turn = jnp.diff(u, axis=-2) / jnp.maximum(0.5 * (length[..., 1:, :] + length[..., :-1, :]), 1e-12)
    both = (length[..., 1:, 0] > 1e-9) & (length[..., :-1, 0] > 1e-9)
    ratio_a = jnp.where(both, speed[..., 0] * jnp.sqrt(jnp.max(jnp.abs(turn) / acc, axis=-1)), 0.0)
    ratio_a = jnp.concatenate([ratio_a, jnp.zeros_like(ratio_a[..., :1])], axis=-1)
    return jnp.maximum(ratio_v, ratio_a)


def normalize_position(p: Array, lo: Array, hi: Array) -> Array:
    """Positions ``[..., n]`` mapped to [-1, 1] over ``[lo, hi]``; continuous joints (infinite
    limits) are wrapped: ``-1 + 2 ((p + pi) / 2 pi mod 1)``."""
    finite = jnp.isfinite(lo) & jnp.isfinite(hi)
    span = jnp.where(finite, hi - lo, 1.0)
    bounded = -1.0 + 2.0 * (p - jnp.where(finite, lo, 0.0)) / span
    if not isinstance(finite, jax.core.Tracer) and bool(np.all(finite)):
        return bounded  # known limits, none continuous: the wrapped branch would be dead work
    wrapped = -1.0 + 2.0 * jnp.mod((p + jnp.pi) / (2.0 * jnp.pi), 1.0)
    return jnp.where(finite, bounded, wrapped)
