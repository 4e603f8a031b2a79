"""ARMAR-4 keeping its balance while its upper body tracks a path (paper 000 §IV-B, docs/method.md §2.4, §4).

The robot is ARMAR-4 of :mod:`mjx_pathtrack.robots.registry` on a floating base (the pelvis
link ``base``) standing on two flat soles on a floor, MJX physics with foot-floor contacts and few
solver iterations. The reference path covers the 18 upper-body joints (torso + two arms):

* ``legs="fixed"`` (18 actions, the papers' ``balancing_reward_fixed_legs`` net): the policy
  moves the upper body only. :func:`make_env` builds it on ``armar4_standing``, whose leg joints
  are welded at their initial pose (0): 24 degrees of freedom instead of 36, twice as fast, and
  as close to the papers' simulator as the servo-held legs; the task's preset steps it at 80 Hz
  (:data:`PHYSICS_SUBSTEPS`), 3x cheaper again at the same fidelity (``benchmarks/bench_balance.py``,
  ``scripts/armar4_pybullet_fidelity.py``). :func:`make_env` runs the physics at the config's
  ``substeps`` per decision step. On ``armar4_legs`` the same task holds the 12 leg
  joints at ``q0`` by their servos (:class:`HeldJointsExecutor`);
* ``legs="controlled"`` (30 actions, ``balancing_reward_controlled_legs``, ``armar4_legs``): the
  leg joints are actuated by the policy too, through the same safe action space (their own
  position, velocity, acceleration and jerk limits); they are not part of the path and start at
  ``q0``.

On top of :class:`~mjx_pathtrack.envs.tracking.PathTrackingEnv` (through its ``task_step`` hook):

* **observation** (``base_sensor=True``) adds 8 values (docs/method.md §4 item 9): the pelvis position
  relative to its start, normalised by ``0.2/sqrt(3)`` m (3); the pelvis orientation quaternion
  (w, x, y, z) with ``w >= 0`` (4); the z-axis tilt normalised over [0, 0.125 rad] (1). All clipped
  to [-1, 1]. Deliberate difference: the published code maps the quaternion from
  [0, 1] to [-1, 1], which clips every negative component to -1 and so hides the direction of a
  small tilt; the components are already in [-1, 1], so we pass them as they are.
* **reward** adds the balance terms of docs/method.md §2.4 (each ``(1 - min(1, x/x_max))**2``):
  pelvis displacement (0.2 m, weight 0.2), orientation ``arccos|q_w| 2/pi`` (0.5, 0.2), z-axis
  tilt (0.125 rad, 2.0) and the mean Cartesian distance of the two wrist target points, commanded
  pose on the moving pelvis vs. reference pose on the initial pelvis (0.4 m, 0.2).
* **termination**: the robot *fell* when the pelvis tilt exceeds ``fall_tilt`` (0.52 rad, the
  published code's optional z-angle termination) or the pelvis centre of mass dropped by more
  than ``fall_drop`` (0.2 m); the episode then ends as a task failure (``task_failed`` metric).

Positions of the pelvis are those of the pelvis link's centre of mass (site ``pelvis`` of the
registry's floating robots, about 0.98 m above the floor, like PyBullet's base position; on
``armar4_standing`` the welded legs move the ``base`` body's own centre of mass, not the site);
its orientation is the body frame's.
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
from mjx_pathtrack import _quiet  # noqa: F401,I001  (before brax / mujoco.mjx: silences their Warp notices)
from mujoco import mjx

from mjx_pathtrack.core import limits as L
from mjx_pathtrack.core import reward as R
from mjx_pathtrack.core import spline as S
from mjx_pathtrack.core.knot_rule import KnotRule
from mjx_pathtrack.envs.action_prior import HoldPrior
from mjx_pathtrack.envs.tracking import EnvConfig, PathTrackingEnv, TrackState
from mjx_pathtrack.envs.executors import MjxExecutor
from mjx_pathtrack.robots.scene import PELVIS_SITE

Array = jax.Array

ROBOT = "armar4_legs"
#: the robot of the fixed-legs task: ``armar4_legs`` with the legs welded at their initial pose
STANDING_ROBOT = "armar4_standing"
#: dataset robot whose path joints are ARMAR-4's 18 upper-body joints (same names and order)
DATASET_ROBOT = "armar4"
LEGS = ("fixed", "controlled")
#: fall thresholds: pelvis tilt [rad] and drop of the pelvis centre of mass [m]
FALL_TILT = 0.52
FALL_DROP = 0.2
#: observation scales (docs/method.md §4 item 9): pelvis position [m], tilt [rad]
BASE_POS_SCALE = 0.2 / np.sqrt(3.0)
TILT_SCALE = 0.125
#: observation blocks the pelvis sensor adds (``base_sensor=True``), in order
BASE_BLOCKS = (("pelvis_position", 3), ("pelvis_quaternion_wxyz", 4), ("pelvis_tilt", 1))
BASE_OBS_SIZE = sum(size for _, size in BASE_BLOCKS)
#: the papers' ARMAR-4 balancing nets (docs/method.md §2.4): alpha 2, no R_action, balance terms
BALANCE_WEIGHTS = R.RewardWeights(distance=2.0, max_deviation=0.9, mean_deviation=0.9, action=0.0,
                                  base_pos=0.2, base_orn=0.2, tilt=2.0, end_point=0.2)
BALANCE_TERMS = ("base_pos", "base_orn", "tilt", "end_point")


class HeldJointsExecutor:
    """An :class:`~mjx_pathtrack.envs.executors.MjxExecutor` of the whole robot driven through a subset
    of its joints: ``active`` (indices into the robot's joints) follow the setpoints, every other
    joint is held at ``hold [n_robot]`` by its servo (setpoint position ``hold``, velocity 0).
    ``execute`` returns the measured positions ``[S+1, len(active)]`` of the active joints."""

    name = "mjx"

    def __init__(self, inner: MjxExecutor, active, hold):
        self.inner = inner
        self.active = np.asarray(active, np.int32)
        self.hold = jnp.asarray(hold, jnp.float32)
        self.substeps = inner.substeps

    def _full(self, q: Array, rest: Array) -> Array:
        return rest.at[..., self.active].set(q)

    def init(self, p0: Array):
        return self.inner.init(self._full(p0, self.hold))

    def execute(self, data, p, v, a0, a1, dt):
        zero = jnp.zeros_like(self.hold)
        data, q, sensors = self.inner.execute(data, self._full(p, self.hold), self._full(v, zero),
                                              self._full(a0, zero), self._full(a1, zero), dt)
        return data, q[:, self.active], sensors

    def scene(self, data) -> dict[str, Array]:
        """The whole robot's ``qpos`` (:meth:`MjxExecutor.scene`)."""
        return self.inner.scene(data)

    @property
    def robot(self):
        """The simulated robot (all of its joints)."""
        return self.inner.robot


#: how far [rad] :func:`standing_home` keeps a joint inside its position limits (half the range
#: where the range is narrower)
HOME_MARGIN = 0.1


def standing_home(robot) -> np.ndarray:
    """Joint positions ``[n]`` [rad] of ``robot`` standing with nearly straight legs and the soles
    flat: ``q0`` clipped into the limits narrowed by ``HOME_MARGIN`` on each side (by half the
    range where that is narrower), and every ankle pitch (``ank1``) turned back by its knee's
    change. ARMAR-4's knees have ``q0 = 0``, 0.035 rad below their lower limit (the margin inside
    the URDF's [0, 1.635]): a policy that controls them must start inside (the safe action space
    moves them in at once otherwise), and away from the limit: at the limit the safe range is
    one-sided ([0, A] at rest), so holding still is the border action -1, which a network only
    approximates, and the fitted hold of ``--init-from`` let the knees wander and the robot fall
    in half the episodes; 0.05 rad inside, the whole range [-A, A] is open. The knees therefore
    start bent by 0.135 rad. A knee bent alone tilts the sole by the same angle, which tips the
    robot over within 2 s standing still; the knee and ankle pitch axes are (anti)parallel, so the
    ankle restores the sole's orientation exactly."""
    import mujoco

    lim = robot.limits
    q0 = np.asarray(robot.q0, np.float64)
    lo, hi = np.asarray(lim.pos_min, np.float64), np.asarray(lim.pos_max, np.float64)
    margin = np.minimum(HOME_MARGIN, (hi - lo) / 2)
    home = np.clip(q0, lo + margin, hi - margin)
    model = robot.mj_model
    data = mujoco.MjData(model)
    data.qpos[:] = robot.qpos0
    mujoco.mj_kinematics(model, data)
    names = list(robot.joint_names)
    for i, name in enumerate(names):
        ankle = name.replace("knee", "ank1")
        if "knee" in name and ankle in names:
            j = names.index(ankle)
            turn = float(np.dot(data.xaxis[model.joint(name).id], data.xaxis[model.joint(ankle).id]))
            home[j] = np.clip(home[j] - turn * (home[i] - q0[i]), lim.pos_min[j], lim.pos_max[j])
    return home.astype(np.float32)


@dataclasses.dataclass(frozen=True)
class BalanceOptions:
    """Task settings: ``legs`` ("fixed": 18 actions, "controlled": 30); ``base_sensor``: add the
    8 pelvis values to the observation; ``fall_tilt`` [rad], ``fall_drop`` [m]: fall thresholds."""

    legs: str = "fixed"
    base_sensor: bool = True
    fall_tilt: float = FALL_TILT
    fall_drop: float = FALL_DROP


class HumanoidBalanceEnv(PathTrackingEnv):
    """Path tracking of ARMAR-4's upper body on its own two feet (see module docstring).

    ``robot``: a loaded floating-base ARMAR-4 :class:`~mjx_pathtrack.robots.registry.Robot`
    (``armar4_standing``: fixed legs only; ``armar4_legs``: both); ``paths``: stacked
    paths over the 18 upper-body joints; ``config``: :class:`~mjx_pathtrack.envs.tracking.EnvConfig` (its
    ``reward`` holds the balance weights, e.g. :data:`BALANCE_WEIGHTS`; ``substeps`` must equal
    ``robot.n_substeps``); ``options``: :class:`BalanceOptions`.
    """

    #: what a task failure (``task_failed``) means here (evaluate.py: "robot fell in x % of the episodes")
    task_failure = "robot_fell"

    def __init__(self, robot, paths: S.Path, max_dis_between_knots: float, config: EnvConfig,
                 options: BalanceOptions = BalanceOptions()):
        if options.legs not in LEGS:
            raise ValueError(f"legs must be one of {LEGS}, got {options.legs!r}")
        if not robot.floating:
            raise ValueError(f"robot {robot.name!r} has no floating base; the balance task needs {ROBOT!r}")
        upper = np.flatnonzero(np.asarray(robot.path_mask))
        if options.legs == "controlled" and len(upper) == robot.n_joints:
            raise ValueError(f"robot {robot.name!r} has no leg joints to control; legs='controlled' needs {ROBOT!r}")
        if options.legs == "fixed" and len(upper) < robot.n_joints:  # legs held at q0 by their servos
            active = upper
            lim = robot.limits
            limits = L.JointLimits(*(jnp.asarray(x)[active] for x in (lim.pos_min, lim.pos_max, lim.vel, lim.acc,
                                                                       lim.jerk)),
                                   names=tuple(robot.joint_names[i] for i in active))
            executor = HeldJointsExecutor(MjxExecutor(robot), active, robot.q0)
            path_joints = np.arange(len(active))
        else:  # every joint acts: controlled legs, or fixed legs welded (a robot without leg joints)
            active = np.arange(robot.n_joints)
            limits = robot.limits
            executor = MjxExecutor(robot)
            path_joints = upper
        self.robot = robot
        self.options = options
        self.active = active
        self.joint_names = tuple(robot.joint_names[i] for i in active)
        home = standing_home(robot)[active]  # joints outside the path (controlled legs) start there
        super().__init__(limits, paths, max_dis_between_knots, config, path_joints=path_joints, home=home,
                         executor=executor)
        data0 = robot.mj_data()
        self._base_body = int(robot.mj_model.body("base").id)
        if robot.mj_model.jnt_type[0] != 0 or robot.mj_model.jnt_bodyid[0] != self._base_body:
            raise ValueError(f"{robot.name}: the first joint must be the free joint of body 'base'")
        self._pelvis = int(robot.mj_model.site(PELVIS_SITE).id)
        self._base0 = jnp.asarray(data0.site_xpos[self._pelvis], jnp.float32)
        self._qpos0 = jnp.asarray(robot.qpos0, jnp.float32)
        self._sites = jnp.asarray(robot.site_ids)
        self._fk_data = mjx.make_data(robot.mjx_model)

    # -- pelvis -----------------------------------------------------------------------------

    def base_state(self, data) -> tuple[Array, Array, Array, Array]:
        """From the executor's ``mjx.Data``: pelvis position relative to its start ``[3]`` [m],
        quaternion ``[4]`` (w, x, y, z; w >= 0), z-axis in the world ``[3]`` and tilt ``[]`` [rad]."""
        pos = data.site_xpos[self._pelvis] - self._base0
        quat = data.qpos[3:7]
        quat = jnp.where(quat[0] < 0, -quat, quat)
        z_axis = data.xmat[self._base_body].reshape(3, 3)[:, 2]
        return pos, quat, z_axis, R.tilt_angle(z_axis)

    def _target_points(self, qpos: Array) -> Array:
        """World positions ``[k, 3]`` of the robot's target sites at ``qpos`` (kinematics only)."""
        data = mjx.kinematics(self.robot.mjx_model, self._fk_data.replace(qpos=qpos))
        return data.site_xpos[self._sites]

    def _robot_q(self, q: Array) -> Array:
        """Positions of all robot joints ``[n_robot]`` from the env's joints ``[n]`` (legs at q0 if fixed)."""
        return jnp.asarray(self.robot.q0, jnp.float32).at[self.active].set(q)

    # -- PathTrackingEnv hooks ----------------------------------------------------------------

    task_name = "balance"

    def extra_observation_blocks(self) -> list[tuple[str, int]]:
        return list(BASE_BLOCKS) if self.options.base_sensor else []

    def observe(self, track: TrackState) -> Array:
        obs = super().observe(track)
        if not self.options.base_sensor:
            return obs
        pos, quat, _, tilt = self.base_state(track.executor)
        extra = jnp.concatenate([pos / BASE_POS_SCALE, quat, (-1.0 + 2.0 * tilt / TILT_SCALE)[None]])
        return jnp.concatenate([obs, jnp.clip(extra, -1.0, 1.0)])

    def task_step(self, before: TrackState, after: TrackState, sensors):
        del before, sensors
        data = after.executor
        pos, quat, z_axis, tilt = self.base_state(data)
        # end points: commanded pose on the current pelvis vs. reference pose on the initial pelvis
        rq = self.robot.qpos_adr
        commanded = self._target_points(data.qpos.at[rq].set(self._robot_q(after.p)))
        path = self.reference(after)
        q_ref = self.home.at[self.path_joints].set(S.point_at(path, after.s))
        reference = self._target_points(self._qpos0.at[rq].set(self._robot_q(q_ref)))
        end_error = jnp.mean(jnp.linalg.norm(commanded - reference, axis=-1))
        terms = R.balance_terms(self.config.reward, pos, quat, z_axis, end_error)
        fell = (tilt > self.options.fall_tilt) | (-pos[2] > self.options.fall_drop)
        return terms, fell, {"tilt": tilt, "end_point_error": end_error}

    def metric_names(self) -> tuple[str, ...]:
        return super().metric_names() + tuple(f"reward/{k}" for k in BALANCE_TERMS) + ("tilt", "end_point_error")


def balance_weights(scale: float = 1.0, base: R.RewardWeights = BALANCE_WEIGHTS) -> R.RewardWeights:
    """``base`` (default: the papers' ARMAR-4 weights) with the four balance terms set to the
    papers' weights (0.2, 0.2, 2.0, 0.2) times ``scale`` (0: the "no balancing reward" variant)."""
    return dataclasses.replace(base, **{k: getattr(BALANCE_WEIGHTS, k) * scale for k in BALANCE_TERMS})


@dataclasses.dataclass(frozen=True)
class TaskConfig:
    """The balance task's own training settings (``TrainConfig.balance``): ``legs``
    (:data:`LEGS`: ``"fixed"``, 18 actions, or ``"controlled"``, 30); ``reward``: scale of the
    papers' balance terms (0: the "no balancing reward" variant); ``leg_prior``
    (:data:`LEG_PRIORS`): ``"hold"`` adds the actions that hold the legs still at
    :func:`standing_home` to the policy's leg actions (controlled legs only; :func:`action_prior`),
    ``"none"``: the network's actions alone, as in the papers."""

    legs: str = "fixed"
    reward: float = 1.0
    leg_prior: str = "none"


#: ``--leg-prior``: what the policy's leg actions are added to (:func:`action_prior`)
LEG_PRIORS = ("none", "hold")


def action_prior(config) -> HoldPrior | None:
    """The action prior of a :class:`~mjx_pathtrack.config.run.TrainConfig`'s policy
    (:mod:`mjx_pathtrack.envs.action_prior`): with ``balance.leg_prior == "hold"`` the
    :class:`~mjx_pathtrack.envs.action_prior.HoldPrior` of the 12 leg joints of ``armar4_legs`` at
    :func:`standing_home` (the policy's actions are added to it); None otherwise. Built from the
    config alone, so that evaluation and export rebuild the training's policy without its
    environment. Raises ``ValueError`` if the prior is asked for without controlled legs."""
    if getattr(config, "task", None) != "balance" or config.balance.leg_prior == "none":
        return None
    if config.balance.leg_prior not in LEG_PRIORS:
        raise ValueError(f"leg_prior must be one of {LEG_PRIORS}, got {config.balance.leg_prior!r}")
    if config.balance.legs != "controlled":
        raise ValueError(f"leg_prior {config.balance.leg_prior!r} needs legs='controlled' (the policy moves no "
                         f"leg with legs={config.balance.legs!r})")
    from mjx_pathtrack.robots import registry as robots

    robot = robots.load_robot(ROBOT, dt=config.env.dt)
    legs = np.flatnonzero(~np.asarray(robot.path_mask, bool))
    return HoldPrior(robot.limits, legs, standing_home(robot), config.env.dt)


#: ``train.py --task balance``: the papers' ARMAR-4 balancing settings (flat option names)
PRESET = dict(robot="armar4", dataset="random", executor="mjx", alpha=2.0, action_reward=0.0,
              duration=20.0, n_next=8, balance_reward=1.0)

#: physics steps per 0.1 s decision step with fixed legs (``--substeps``; 80 Hz, servo bandwidth
#: 133 rad/s by the registry's rule): 3x cheaper than the papers' 240 Hz and as close to their
#: simulator (the welded legs against PyBullet on 200 fast motions: same fall/no-fall 93 % / 95 %,
#: peak-tilt ratio 0.89 / 0.82; at 240 Hz 94 % / 96 %, 0.88 / 0.86; docs/results.md "Cost of the
#: step"). Not for leg joints: servo-held legs at 80 Hz give too much (81 %, peak ratio 2.2).
PHYSICS_SUBSTEPS = 8

#: what the task's preset adds per ``--legs``: the physics rate (controlled legs: the papers' 240 Hz)
LEGS_PRESETS = {"fixed": dict(substeps=PHYSICS_SUBSTEPS), "controlled": dict(substeps=24)}


def make_env(config, split: str = "train", paths: S.Path | None = None, max_dis: float | None = None,
             env_config: EnvConfig | None = None, root=None, base_sensor: bool = True) -> HumanoidBalanceEnv:
    """The balance environment of a :class:`~mjx_pathtrack.config.run.TrainConfig` (``task="balance"``,
    ``robot="armar4"``: the dataset of ARMAR-4's upper-body paths; ``balance``: :class:`TaskConfig`).
    ``paths``/``max_dis``/``env_config`` replace the dataset split, its knot spacing and the
    config's :class:`EnvConfig` (evaluation on user paths or whole paths); ``root``: the dataset
    root (default ``config.dataset_root``); ``base_sensor`` false: no pelvis observation (a plain
    tracking policy on the floating base, :func:`floating_base_config`)."""
    from mjx_pathtrack.paths import datasets
    from mjx_pathtrack.robots import registry as robots

    root = config.dataset_root if root is None else root
    if config.robot != DATASET_ROBOT:
        raise ValueError(f"the balance task tracks paths of robot {DATASET_ROBOT!r} (ARMAR-4's upper body), "
                         f"got robot {config.robot!r}")
    if config.executor != "mjx":
        raise ValueError(f"the balance task needs the mjx executor (floating base physics), got {config.executor!r}")
    robot = robots.load_robot(STANDING_ROBOT if config.balance.legs == "fixed" else ROBOT, dt=config.env.dt,
                              sim_dt=config.env.dt / config.env.substeps)
    if max_dis is None:
        meta = datasets.read_config(config.robot, config.dataset, root)
        upper = [n for n, m in zip(robot.joint_names, robot.path_mask) if m]
        if list(meta.get("joint_names", upper)) != upper:
            raise ValueError(f"dataset {config.robot}/{config.dataset} joints {meta['joint_names']} differ from "
                             f"ARMAR-4's upper body {upper}")
        max_dis = float(meta["max_dis_between_knots"])
        knot_rule = KnotRule.of_dataset(meta)
    else:
        knot_rule = None   # the caller's scale: the papers' curvature rule capped at it
    if paths is None:
        paths = datasets.load_paths(config.robot, config.dataset, split, root=root)
    env_config = config.env_config() if env_config is None else env_config
    env = HumanoidBalanceEnv(robot, paths, max_dis, env_config,
                             BalanceOptions(legs=config.balance.legs, base_sensor=base_sensor))
    if knot_rule is not None:
        env.knot_rule = knot_rule
    return env


def floating_base_config(config):
    """The balance-task config that runs a plain ARMAR-4 tracking run's policy (``robot="armar4"``,
    trained on the fixed base) standing on the floor with its legs fixed: the papers' Table VIII
    "no balancing reward" row, which evaluates the plain target-point net on the floating base.
    Its training settings stay; MJX physics at the fixed-legs rate, no balance reward. Build the
    environment with ``make_env(..., base_sensor=False)``: the policy never saw the pelvis."""
    if config.task != "tracking" or config.robot != DATASET_ROBOT:
        raise ValueError(f"a floating-base evaluation takes a plain tracking run of robot {DATASET_ROBOT!r} "
                         f"(ARMAR-4's upper body), got task {config.task!r} on robot {config.robot!r}")
    return config.replace(task="balance", executor="mjx", legs="fixed", balance_reward=0.0,
                          substeps=LEGS_PRESETS["fixed"]["substeps"])


def eval_robot(config):
    """The robot whose joints are the environment's actions (Cartesian metrics in evaluation):
    ``armar4`` (fixed legs: the same 18 joints on a static base) or ``armar4_legs``."""
    from mjx_pathtrack.robots import registry as robots

    return robots.load_robot(DATASET_ROBOT if config.balance.legs == "fixed" else ROBOT, dt=config.env.dt)
