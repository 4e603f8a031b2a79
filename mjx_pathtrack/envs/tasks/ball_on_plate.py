"""Ball on plate (paper 000 §IV-B, docs/method.md §2.4, §4, docs/robots.md §4): track a ball-balancing path with the
iiwa while a free ball rolls on the plate at its flange (MJX physics, ``iiwa_ball`` scene).

:class:`BallOnPlateEnv` is a :class:`~mjx_pathtrack.envs.tracking.PathTrackingEnv` whose executor
(:class:`BallExecutor`) also simulates the ball; it adds, per step:

* observation (docs/method.md §4 item 8): the Cartesian reference point (FK of the reference at
  the new arc position, target site ``iiwa_link_ee``) normalised over x, y in [-1, 1] m, z in
  [-0.7, 1.3] m; the reference point minus the executed end point, normalised by 0.1 m; with
  ``sensor``, the ball position in the plate frame of the previous and current step,
  ``(x_rel, y_rel) = xy / (0.5 plate size - 0.03 m)``. Size 72 with the sensor, 68 without
  (``N = 4``, 7 joints), as the papers' ball nets;
* reward ``ball * R_ball`` (:func:`mjx_pathtrack.core.reward.ball_reward`). The published code computes
  ``1 - max(x_rel, y_rel)`` without ``abs``, so only displacements towards +x/+y are penalised --
  a bug; we use the absolute displacement ``1 - max(|x_rel|, |y_rel|)``;
* optional reward ``cartesian * R_cart`` (:func:`mjx_pathtrack.core.reward.cartesian_deviation_reward`,
  not in the papers: weight 0 there): the executed end point's distance from the reference point
  at the new arc position, threshold 0.1 m. Balancing tilts the plate about the wrist, which
  moves the target point 0.126 m from it; the joint-space deviation terms cannot tell a tilt
  about the target point (which keeps it on the path) from one that moves it;
* termination when the ball leaves the plate (``|x_rel| >= 1`` or ``|y_rel| >= 1`` or its centre
  below the plate surface): metric ``ball_fell``.

Per episode the ball's radius (20-36 mm), mass (2-203 g), rolling and torsional friction
(1e-4..6e-4, the papers' ranges; contact ``condim = 6`` here so that they act) and start position
(±0.0797 m x ±0.0458 m) are drawn. The ball's model parameters are re-derived every step from a
per-environment key, so a batch of environments shares one ``mjx.Model``.

The papers' ball nets (docs/method.md §2.4, §3, docs/training.md §1): N = 4, alpha = 4, deviation weights 0.9/0.9,
no action reward, 6 s per path, whole paths (no sub-paths), no forced braking at the end (the
episode runs to its time budget).
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np

from mjx_pathtrack.core import reward as R
from mjx_pathtrack.core import spline as S
from mjx_pathtrack.core.knot_rule import KnotRule
from mjx_pathtrack.envs.tracking import EnvConfig, PathTrackingEnv
from mjx_pathtrack.envs.tasks.ball_executor import FRICTION_RANGE, BallExecutor, BallState, sample_friction  # noqa: F401  (re-exported)
from mjx_pathtrack.envs.tasks.plate_executor import PrescribedPlateExecutor
from mjx_pathtrack.envs.tasks.rolling_ball import RollingBallExecutor

Array = jax.Array

#: docs/method.md §4 item 8: Cartesian range of the reference point [m] (scene 8) and of the relative point
TARGET_RANGE_LO = (-1.0, -1.0, -0.7)
TARGET_RANGE_HI = (1.0, 1.0, 1.3)
RELATIVE_RANGE = 0.1
#: dataset of the task (splines/iiwa/ball_balancing)
DATASET = ("iiwa", "ball_balancing")


#: observation blocks added after the path-tracking observation (docs/method.md §4 item 8), in order
CARTESIAN_BLOCKS = (("target_point", 3), ("target_minus_executed_point", 3))
SENSOR_BLOCKS = (("ball_xy_previous", 2), ("ball_xy", 2))  # only with the ball sensor


def extra_blocks(sensor: bool) -> tuple[tuple[str, int], ...]:
    """The blocks the task adds to the path-tracking observation, with or without the ball sensor."""
    return CARTESIAN_BLOCKS + (SENSOR_BLOCKS if sensor else ())


@dataclasses.dataclass(frozen=True)
class BallConfig:
    """Task settings. ``reward``: weight of R_ball (0: off); ``sensor``: ball position in the
    observation; ``terminate``: end the episode when the ball leaves the plate; ``cartesian``:
    weight of R_cart (module docstring; 0: off, the papers')."""

    reward: float = 1.0
    sensor: bool = True
    terminate: bool = True
    cartesian: float = 0.0

    def __post_init__(self):
        for name in ("reward", "cartesian"):
            value = getattr(self, name)
            if not (np.isfinite(value) and value >= 0):
                raise ValueError(f"BallConfig.{name} must be a finite number >= 0, got {value}")


def env_config(duration: float = 6.0, terminate_deviation: float | None = 0.25, **overrides) -> EnvConfig:
    """The papers' ball-net settings (see module docstring) as an :class:`EnvConfig`."""
    weights = R.RewardWeights(distance=4.0, max_deviation=0.9, mean_deviation=0.9, action=0.0)
    base = dict(n_next=4, duration=duration, start_range=(0.0, 0.0), min_fraction=1.0, max_fraction=1.0,
                terminate_deviation=terminate_deviation, brake_at_end=False, terminate_on_stop=False,
                deviation_weights=(1.0, 1.0, 1.0, 0.9, 0.8, 0.7, 0.6), reward=weights)
    return EnvConfig(**{**base, **overrides})


class BallOnPlateEnv(PathTrackingEnv):
    """Path tracking with a ball on the plate (module docstring). Arguments as
    :class:`PathTrackingEnv` with a :class:`BallExecutor`; ``ball``: :class:`BallConfig`."""

    def __init__(self, limits, paths, max_dis_between_knots, config: EnvConfig, executor: BallExecutor,
                 ball: BallConfig = BallConfig(), path_joints=None, home=None):
        if not isinstance(executor, BallExecutor):
            raise ValueError("BallOnPlateEnv needs a BallExecutor")
        super().__init__(limits, paths, max_dis_between_knots, config, path_joints, home, executor)
        self.ball_config = ball
        self._half_range = jnp.asarray(R.BALL_HALF_RANGE, jnp.float32)

    task_name = "ball_on_plate"
    #: what a task failure (``task_failed``) means here (evaluate.py: "ball fell in x % of the episodes")
    task_failure = "ball_fell"

    def extra_observation_blocks(self) -> list[tuple[str, int]]:
        return list(extra_blocks(self.ball_config.sensor))

    def metric_names(self) -> tuple[str, ...]:
        return super().metric_names() + ("reward/ball", "reward/cartesian", "ball_fell")

    def initial_state(self, rng: Array, index: Array | None = None):
        track = super().initial_state(rng, index)
        executor = self.executor.randomize(track.executor, jax.random.fold_in(rng, 7))
        return track._replace(executor=executor)

    def off_plate(self, ball: Array) -> Array:
        """True if the ball centre ``[3]`` (plate frame) is beyond the normalised range or below the surface."""
        rel = ball[:2] / self._half_range
        return jnp.any(jnp.abs(rel) >= 1.0) | (ball[2] < 0.0)

    def transition(self, track, action: Array, fastest_stop: Array | bool = False):
        new, reward, done, metrics = super().transition(track, action, fastest_stop)
        # a fall also spoils success when it does not end the episode (trained without the ball)
        metrics = {**metrics, "success": metrics["success"] * (1.0 - metrics["ball_fell"])}
        return new, reward, done, metrics

    def task_update(self, before, after, sensors):
        """The Cartesian reference point at the new arc position and the executed end point's
        offset from it (``executor.target``/``relative``: observation and R_cart)."""
        del before, sensors
        q_ref = self.home.at[self.path_joints].set(S.point_at(self.reference(after), after.s))
        pos, _ = self.executor.robot.fk(jnp.stack([q_ref, after.executor.q]))
        return after._replace(executor=after.executor._replace(target=pos[0, 0], relative=pos[0, 0] - pos[1, 0]))

    def task_step(self, before, after, sensors):
        """R_ball, R_cart (weight 0: a constant 0) and the fall (``ball_fell``; a task failure that
        ends the episode when ``ball_config.terminate``)."""
        del before, sensors
        cfg, ex = self.ball_config, after.executor
        fell = self.off_plate(ex.ball)
        failed = fell if cfg.terminate else jnp.zeros((), bool)
        cart = (jnp.zeros(()) if cfg.cartesian == 0 else
                cfg.cartesian * R.cartesian_deviation_reward(jnp.linalg.norm(ex.relative)))
        return ({"ball": cfg.reward * R.ball_reward(ex.ball[:2]), "cartesian": cart}, failed,
                {"ball_fell": fell.astype(jnp.float32)})

    def observe(self, track) -> Array:
        ex = track.executor
        lo, hi = jnp.asarray(TARGET_RANGE_LO), jnp.asarray(TARGET_RANGE_HI)
        extras = [-1.0 + 2.0 * (ex.target - lo) / (hi - lo), ex.relative / RELATIVE_RANGE]
        if self.ball_config.sensor:
            extras += [ex.ball_prev[:2] / self._half_range, ex.ball[:2] / self._half_range]
        return jnp.clip(jnp.concatenate([super().observe(track)] + extras), -1.0, 1.0)


#: the task's physics (``make_env(physics=...)``): ``"arm"``, the whole servo-driven arm with the
#: plate and the ball in MJX (:class:`BallExecutor`, the reference); ``"plate"``, the plate's
#: motion prescribed by the setpoints and only the plate and the ball in MJX
#: (:class:`~mjx_pathtrack.envs.tasks.plate_executor.PrescribedPlateExecutor`, 1.2x the
#: reference's speed); ``"rolling"``, the plate prescribed and the ball rolling on it in pure JAX
#: (:class:`~mjx_pathtrack.envs.tasks.rolling_ball.RollingBallExecutor`, 18-21x; the preset's)
PHYSICS = ("arm", "plate", "rolling")


def make_env(split: str = "train", config: EnvConfig | None = None, ball: BallConfig = BallConfig(),
             reflections: bool = False, dt: float = 0.1, root=None, physics: str = "arm",
             paths: S.Path | None = None) -> BallOnPlateEnv:
    """The task on ``splines/iiwa/ball_balancing/<split>`` (or on ``paths``, a stacked batch of
    level-plate paths: a user's); ``reflections``: add the dataset's reflected copies of every
    path (docs/paths.md §5, 4x augmentation); ``physics``: :data:`PHYSICS`."""
    if physics not in PHYSICS:
        raise ValueError(f"unknown ball physics {physics!r}; known: {', '.join(PHYSICS)}")
    from mjx_pathtrack.paths import datasets
    from mjx_pathtrack.robots import registry as robots
    from mjx_pathtrack.paths.ball import REFLECTION_VECTORS, reflect_paths

    robot = robots.load_robot("iiwa_ball", dt=dt)
    meta = datasets.read_config(*DATASET, root)
    if paths is None:
        knots = datasets.load_split(*DATASET, split, root)
        if reflections:
            knots = reflect_paths(knots, meta.get("reflection_vectors") or REFLECTION_VECTORS)
        paths = S.stack_fits(S.fit_spline(k) for k in knots)
    cfg = env_config() if config is None else config
    if physics == "plate":

        executor = PrescribedPlateExecutor(robot)
    elif physics == "rolling":

        executor = RollingBallExecutor(robot)
    else:
        executor = BallExecutor(robot)
    env = BallOnPlateEnv(robot.limits, paths, float(meta["max_dis_between_knots"]), cfg, executor, ball,
                         home=robot.q0)
    env.knot_rule = KnotRule.of_dataset(meta)
    return env


@dataclasses.dataclass(frozen=True)
class TaskConfig:
    """The task's own training settings (``TrainConfig.ball_on_plate``): ``reward``: weight of
    R_ball; 0: trained without the ball (neither observed, rewarded nor ending the episode);
    ``physics``: :data:`PHYSICS` (default ``"arm"``, the reference; the preset trains with
    ``"rolling"``, docs/results.md "Ball on plate"); ``cartesian_reward``: weight of R_cart
    (:class:`BallConfig` ``cartesian``; 0: the papers')."""

    reward: float = 1.0
    physics: str = "arm"
    cartesian_reward: float = 0.0


#: ``train.py --task ball_on_plate``: the papers' ball-net settings (N 4, alpha 4, 6 s, no action
#: reward) on the rolling ball, with both deviation weights 2 instead of 0.9 (``beta``), R_ball
#: weight 2 instead of 1 and R_jerk weight 1 (not in the papers: it reduces the bang-bang chatter
#: the papers' reward pays for), the default recipe's PPO sizes and 16 M steps (the 40 M run's
#: training evaluation at 16 M: end reached 85 %, ball fell 17 %); ``--preset paper`` trains 40 M steps
#: (72 min on 2 CPU cores, 47 of them shared with a second run): in the full-arm
#: MJX scene the ball fell in 2.0 % of the 200 test paths, end reached 98.0 % at 2.56 s, 3.5 cm
#: Cartesian deviation; with the papers' weights 4.5 %, 95.5 %, 2.48 s, 3.9 cm (docs/results.md
#: "Ball on plate") (flat option names, :data:`mjx_pathtrack.config.run.FLAT_NAMES`)
PRESET = dict(task="ball_on_plate", robot="iiwa", dataset="ball_balancing", executor="mjx", n_next=4, alpha=4.0,
              beta=2.0, action_reward=0.0, jerk_reward=1.0, duration=6.0, terminate_deviation=0.25, ball_reward=2.0,
              ball_physics="rolling", num_envs=256, batch_size=256, num_minibatches=8, unroll_length=20,
              num_updates_per_batch=4, num_timesteps=16_000_000, num_evals=9, eval_episodes=128)


def make_task_env(config, split: str = "train", root=None, evaluation: bool | None = None,
                  paths: S.Path | None = None) -> BallOnPlateEnv:
    """The task for a :class:`~mjx_pathtrack.config.run.TrainConfig` (``task='ball_on_plate'``).

    ``config.ball_on_plate.reward > 0``: R_ball with that weight, ball sensor observed, episode
    ends when the ball falls. ``reward == 0``: the papers' "no balancing reward" net -- trained on
    the same paths with the ball simulated but neither observed, rewarded nor ending the episode;
    ``evaluation`` (default: the test split) still ends episodes when it falls (the reported
    failure). The train split gets the 4 reflections of every path (docs/paths.md §5). ``paths``:
    level-plate paths (a user's, checked) instead of the split."""
    evaluation = split == "test" if evaluation is None else evaluation
    weight = float(config.ball_on_plate.reward)
    with_ball = weight > 0
    env_cfg = dataclasses.replace(config.env_config(), start_range=(0.0, 0.0), min_fraction=1.0, max_fraction=1.0,
                                  brake_at_end=False, terminate_on_stop=False)
    ball = BallConfig(reward=weight, sensor=with_ball, terminate=with_ball or evaluation,
                      cartesian=float(config.ball_on_plate.cartesian_reward))
    root = config.dataset_root if root is None else root
    return make_env(split, env_cfg, ball, reflections=split == "train" and paths is None, dt=config.env.dt, root=root,
                    physics=config.ball_on_plate.physics, paths=paths)
