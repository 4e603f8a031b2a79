"""The training configuration: ``TrainConfig`` (one run, saved as ``config.json``), nested by
concern, the flat option names the command line, sweep files and old ``config.json`` files use,
and the validation that names a bad option before anything is written or compiled.

``TrainConfig`` holds what the run trains on (robot, task, dataset, executor, seed) and one typed
block per concern::

    TrainConfig(env=EnvConfig(reward=RewardWeights(...)),   # episode, observation, reward
                ppo=PPOConfig(...),                           # the algorithm and its budget
                network=NetworkConfig(...),                   # policy / value networks, std
                eval=EvalConfig(...),                         # evaluations during training
                ball_on_plate=ball_on_plate.TaskConfig(...),  # the tasks' own settings
                balance=humanoid_balance.TaskConfig(...))

Every option also has a *flat name* (:data:`FLAT_NAMES`): ``--alpha`` on the command line,
``alpha`` in a sweep grid, ``config.get("alpha")``, ``config.replace(alpha=2.0)``. A flat name
maps to one or more dotted paths (``beta`` sets both deviation weights); dotted paths
(``config.replace(**{"env.substeps": 48})``) reach every field. The papers' names ``alpha`` and
``beta`` are flat names of ``env.reward.distance`` and ``env.reward.max_deviation`` /
``mean_deviation``: the weight of a reward term carries the term's name.
"""

from __future__ import annotations

import dataclasses
from typing import Any

import numpy as np

from mjx_pathtrack.core import reward as R
from mjx_pathtrack.deploy.networks import NetworkConfig, parse_noise_scale
from mjx_pathtrack.envs.registry import EXECUTORS, FACTORIES
from mjx_pathtrack.envs.tasks import ball_on_plate, humanoid_balance
from mjx_pathtrack.envs.tracking import END_BRAKING, END_STOP, KNOTS_FRAMES, EnvConfig
from mjx_pathtrack.paths import datasets
from mjx_pathtrack.robots import registry as robots
from mjx_pathtrack.config.stored import PARAMS_FILE, params_file
from mjx_pathtrack.config.options import ConfigError, Options, differences, leaves  # noqa: F401  (re-exported)


#: task variants (``TrainConfig.task``): plain path tracking or a sensory-feedback task (mjx_pathtrack.envs.tasks)
TASKS = tuple(FACTORIES)


#: per-path-joint deviation weights of the papers' nets (docs/method.md §2.5)
_IIWA_W = (1.0, 1.0, 1.0, 0.9, 0.8, 0.7, 0.6)


_ARMAR4_W = (1.0, 1.0) + 2 * (1.0, 1.0, 1.0, 1.0, 0.9, 0.8, 0.7, 0.6)


DEVIATION_WEIGHTS = {"iiwa": _IIWA_W, "iiwa_ball": _IIWA_W,
                     "armar6": (1.0,) + 2 * (0.95, 0.95, 0.95, 0.95, 0.9, 0.8, 0.7, 0.6),
                     "armar4": _ARMAR4_W, "armar4_legs": _ARMAR4_W}


@dataclasses.dataclass(frozen=True)
class PPOConfig:
    """The PPO algorithm and its budget. Every field but ``final_learning_rate`` is an argument of
    Brax's ``ppo.train`` under the same name (:meth:`brax_kwargs`).

    Tuned for Brax on a CPU budget (the papers' RLlib settings in docs/training.md §1 use
    300k-sample batches and lr 5e-5 over days). ``final_learning_rate``: None: a constant
    learning rate; a number: geometric from ``learning_rate`` at the start to this value at the
    end of training (:func:`mjx_pathtrack.rl.ppo.learning_rate_scale`): with the shrinking std the
    updates would otherwise grow (KL ~ 1/std**2) and break the policy late in training."""

    num_timesteps: int = 9_600_000
    num_envs: int = 256
    learning_rate: float = 3e-4
    final_learning_rate: float | None = 3e-5
    entropy_cost: float = 1e-3
    discounting: float = 0.99
    gae_lambda: float = 0.95
    clipping_epsilon: float = 0.2
    unroll_length: int = 20
    batch_size: int = 256
    num_minibatches: int = 8
    num_updates_per_batch: int = 4

    def brax_kwargs(self) -> dict[str, Any]:
        """The keyword arguments of ``brax.training.agents.ppo.train.train`` this config sets
        (Brax has no learning-rate schedule: a config with one is refused)."""
        if self.final_learning_rate is not None:
            raise ValueError("Brax's ppo.train has no learning-rate schedule: set final_learning_rate to None")
        return {f.name: getattr(self, f.name) for f in dataclasses.fields(self) if f.name != "final_learning_rate"}

    @property
    def steps_per_iteration(self) -> int:
        """Environment steps of one training iteration (all minibatches of one batch)."""
        return self.batch_size * self.unroll_length * self.num_minibatches


@dataclasses.dataclass(frozen=True)
class EvalConfig:
    """Evaluations during training: ``num_evals`` evaluation points (the first before training),
    each on ``episodes`` test-split episodes, deterministic and sampled."""

    num_evals: int = 7
    episodes: int = 128


def training_env() -> EnvConfig:
    """The environment settings of a new training run: this package's recipe, not the papers'
    :class:`EnvConfig` defaults (docs/results.md "Learning recipe"): knots relative to the
    position (PPO learns far faster), predictive braking (the robot stops at the end instead of
    overshooting it), the stop at the end knot (the final deviation halves for 2-3 % more
    time), and alpha 3 (the papers' iiwa nets: 2; faster at the same budget)."""
    return EnvConfig(knots_frame="relative", end_braking="predictive", end_stop="end_knot",
                     reward=R.RewardWeights(distance=3.0))


@dataclasses.dataclass(frozen=True)
class TrainConfig(Options):
    """Everything that defines a training run (saved as ``config.json`` in the run directory).

    ``robot``, ``task`` (:data:`TASKS`), ``dataset`` (of the robot, under ``dataset_root``; None:
    the committed ``splines/``), ``num_train_paths``: regenerate the train split with this many
    paths (deterministic, into ``<run>/data``) when the dataset's has fewer (0: train on the split
    as it is; :mod:`mjx_pathtrack.paths.train_data`), ``executor`` (:data:`EXECUTORS`), ``seed``,
    ``init_from``: a finished run directory whose parameters (policy, value, observation
    normaliser; its ``params.msgpack``) the run starts from instead of random ones (fine-tuning: same
    observation, action and network sizes; the optimiser and the schedules start afresh); then one
    block per concern (module docstring). ``env.deviation_weights`` None: the robot's
    (:data:`DEVIATION_WEIGHTS`)."""

    robot: str = "iiwa"
    task: str = "tracking"
    dataset: str = "random"
    dataset_root: str | None = None
    num_train_paths: int = 0
    executor: str = "kinematic"
    seed: int = 0
    init_from: str | None = None
    env: EnvConfig = dataclasses.field(default_factory=training_env)
    ppo: PPOConfig = PPOConfig()
    network: NetworkConfig = NetworkConfig()
    eval: EvalConfig = EvalConfig()
    ball_on_plate: ball_on_plate.TaskConfig = ball_on_plate.TaskConfig()
    balance: humanoid_balance.TaskConfig = humanoid_balance.TaskConfig()

    def env_config(self) -> EnvConfig:
        """The :class:`EnvConfig` the task's environment gets: ``env`` with the robot's deviation
        weights (unless set) and, for the balance task, its balance terms."""
        env = self.env
        if env.deviation_weights is None:
            env = dataclasses.replace(env, deviation_weights=DEVIATION_WEIGHTS.get(self.robot))
        if self.task == "balance":
            env = dataclasses.replace(env, reward=humanoid_balance.balance_weights(self.balance.reward, env.reward))
        return env

    @classmethod
    def upgrade_flat(cls, data: dict[str, Any]) -> dict[str, Any]:
        return _upgrade_flat(data)


def _upgrade_flat(data: dict[str, Any]) -> dict[str, Any]:
    """Flat ``config.json`` values of an old run with the defaults of its time filled in."""
    # runs saved before the option existed observed absolute knots (the default since is relative)
    data.setdefault("knots_frame", "absolute")
    # ... and learned their policy std (the default since is a schedule)
    data.setdefault("final_noise_std", None)
    # ... and, before these options existed, braked at the end, kept the learning rate and had
    # a value network that saw the policy's observation only
    data.setdefault("end_braking", "at_end")
    data.setdefault("end_stop", "fastest")  # ... and stopped every joint as fast as it could
    data.setdefault("final_learning_rate", None)
    data.setdefault("privileged_critic", False)
    return data


#: the environment options with a flat name (``--dt``, ...); every other ``EnvConfig`` field is
#: reached by its dotted path (``env.substeps``)
_ENV_OPTIONS = ("dt", "n_next", "substeps", "knots_frame", "terminate_deviation", "end_tolerance", "end_braking", "end_stop",
                "end_knot_tolerance", "duration", "observe_deviation",
                "observe_speed_limits", "train_terminate_deviation")

#: flat option name -> the dotted paths it sets (the command line's ``--name``, sweep grid keys,
#: the keys of a flat ``config.json``)
FLAT_NAMES: dict[str, tuple[str, ...]] = {
    **{name: (name,) for name in ("robot", "task", "dataset", "dataset_root", "num_train_paths", "executor", "seed",
                                  "init_from")},
    **{name: (f"env.{name}",) for name in _ENV_OPTIONS},
    "alpha": ("env.reward.distance",),
    "beta": ("env.reward.max_deviation", "env.reward.mean_deviation"),
    "deviation_threshold": ("env.reward.deviation_threshold",),
    "action_reward": ("env.reward.action",),
    "jerk_reward": ("env.reward.jerk",),
    **{f.name: (f"ppo.{f.name}",) for f in dataclasses.fields(PPOConfig)},
    **{f.name: (f"network.{f.name}",) for f in dataclasses.fields(NetworkConfig)},
    "num_evals": ("eval.num_evals",),
    "eval_episodes": ("eval.episodes",),
    "ball_reward": ("ball_on_plate.reward",),
    "ball_physics": ("ball_on_plate.physics",),
    "cartesian_reward": ("ball_on_plate.cartesian_reward",),
    "legs": ("balance.legs",),
    "balance_reward": ("balance.reward",),
    "leg_prior": ("balance.leg_prior",),
}


TrainConfig.FLAT_NAMES = FLAT_NAMES


#: the allowed values of the options that take one of a few (flat name -> values): the
#: command line's choices and :func:`validate_config`'s check
CHOICES: dict[str, tuple[str, ...]] = {"executor": EXECUTORS, "task": TASKS, "knots_frame": KNOTS_FRAMES,
                                       "end_braking": END_BRAKING, "end_stop": END_STOP,
                                       "ball_physics": ball_on_plate.PHYSICS, "leg_prior": humanoid_balance.LEG_PRIORS}


def validate_config(config: TrainConfig, devices: int = 1) -> None:
    """Raise :class:`ConfigError` naming the option (its flag) unless every option of ``config``
    can work: before anything is written or compiled."""
    c = config
    get = c.get

    def fail(option, message):
        raise ConfigError(f"--{option.replace('_', '-')}: {message}")

    for name, allowed in CHOICES.items():
        if get(name) not in allowed:
            fail(name, f"{get(name)!r} is not one of {', '.join(allowed)}")
    if c.task != "balance" and c.robot not in robots.known_robots():
        fail("robot", f"unknown robot {c.robot!r}; known: {', '.join(robots.known_robots())}")
    if c.env.observe_deviation and c.task != "tracking":
        fail("observe_deviation", f"the deviation block is built for the tracking task, not {c.task!r}")
    if c.env.observe_speed_limits and c.task != "tracking":
        fail("observe_speed_limits", f"the speed-limit block is built for the tracking task, not {c.task!r}")
    if c.task == "balance" and c.balance.legs not in humanoid_balance.LEGS:
        fail("legs", f"{c.balance.legs!r} is not one of {', '.join(humanoid_balance.LEGS)}")
    if c.balance.leg_prior != "none" and (c.task != "balance" or c.balance.legs != "controlled"):
        fail("leg_prior", f"{c.balance.leg_prior!r} adds to the policy's leg actions: it needs --task balance "
                          f"--legs controlled")
    for name in ("dt", "duration", "end_knot_tolerance", "learning_rate", "init_noise_std", "mean_init_scale",
                 "deviation_threshold", "terminate_deviation"):
        value = get(name)
        if not (value is not None and np.isfinite(value) and value > 0):
            fail(name, f"must be a finite number > 0, got {value}")
    for name in ("alpha", "beta", "action_reward", "jerk_reward", "entropy_cost", "end_tolerance", "ball_reward", "cartesian_reward",
                 "balance_reward"):
        for path in TrainConfig.paths(name):  # (beta: both deviation weights)
            _check_nonnegative(name, get(path), fail)
    train_bar = get("train_terminate_deviation")
    if train_bar is not None:
        if not (np.isfinite(train_bar) and train_bar > 0):
            fail("train_terminate_deviation", f"must be a finite number > 0, got {train_bar}")
        if get("terminate_deviation") is not None and train_bar > get("terminate_deviation"):
            fail("train_terminate_deviation", f"{train_bar} is above --terminate-deviation "
                                              f"{get('terminate_deviation')} (the bar the policy is judged at)")
    for name, lo, hi in (("discounting", 0.0, 1.0), ("gae_lambda", 0.0, 1.0), ("clipping_epsilon", 0.0, 1.0)):
        value = get(name)
        if not (np.isfinite(value) and lo < value <= hi):
            fail(name, f"must be in ({lo:g}, {hi:g}], got {value}")
    for name in ("final_noise_std", "final_learning_rate", "mean_clip"):
        value = get(name)
        if value is not None and not (np.isfinite(value) and value > 0):
            fail(name, f"must be a finite number > 0 (or unset), got {value}")
    for name in ("num_envs", "num_timesteps", "unroll_length", "batch_size", "num_minibatches",
                 "num_updates_per_batch", "num_evals", "eval_episodes", "n_next", "substeps"):
        value = get(name)
        if not value >= 1:
            fail(name, f"must be >= 1, got {value}")
    if c.num_train_paths < 0:
        fail("num_train_paths", f"must be >= 0, got {c.num_train_paths}")
    if c.init_from is not None and params_file(c.init_from) is None:
        fail("init_from", f"{c.init_from}: no {PARAMS_FILE} there (the directory of a finished run)")
    for entry in c.network.noise_scale:
        try:
            parse_noise_scale(entry)
        except ValueError as e:
            fail("noise_scale", str(e))
    if c.network.noise_scale and c.network.final_noise_std is None:
        fail("noise_scale", "scales the scheduled std; set --final-noise-std (a learned std is not scaled)")
    for name in ("policy_layers", "value_layers"):
        if not get(name) or min(get(name)) < 1:
            fail(name, f"needs at least one layer, each of size >= 1, got {list(get(name))}")
    p = c.ppo
    if p.num_envs % devices:
        fail("num_envs", f"{p.num_envs} is not a multiple of the {devices} devices it is split over")
    if (p.batch_size * p.num_minibatches) % p.num_envs:
        fail("batch_size", f"batch_size * num_minibatches ({p.batch_size} * {p.num_minibatches} = "
                           f"{p.batch_size * p.num_minibatches}) must be a multiple of --num-envs ({p.num_envs})")
    if c.task != "balance" and (c.executor == "mjx" or c.task == "ball_on_plate"):
        steps = c.env.dt / robots.SIM_DT
        if abs(steps - round(steps)) > 1e-6:
            fail("dt", f"{c.env.dt} s must be a whole multiple of the physics step {robots.SIM_DT:.6g} s with MJX physics")
        if c.env.substeps != round(steps):
            fail("substeps", f"with MJX physics (physics step {robots.SIM_DT:.6g} s) the sub-steps are the physics "
                             f"steps per decision step: {round(steps)} at --dt {c.env.dt}, got {c.env.substeps}")
    if c.task == "tracking":
        try:
            datasets.read_config(c.robot, c.dataset, c.dataset_root)
        except datasets.DatasetError as e:
            known = datasets.known_kinds(c.robot, c.dataset_root)
            fail("dataset", f"{e}" + (f"; datasets of {c.robot}: {', '.join(known)}" if known else ""))


def _check_nonnegative(name: str, value, fail) -> None:
    if not (np.isfinite(value) and value >= 0):
        fail(name, f"must be a finite number >= 0, got {value}")
