"""PPO training of the path-tracking policy: config and its validation, environment wiring,
the run directory, progress, logs, exact checkpoints and resume. ``train.py`` at the repository
root is the command-line front end.

The algorithm is :mod:`mjx_pathtrack.ppo` (Brax's PPO pieces as a pure function of the whole
learner state): every evaluation interval ends with a checkpoint of that state, so a run killed
at any point and resumed with ``resume=True`` ends with the same parameters as an uninterrupted
one (same machine, same device count).

Multi-device: the environments are split over the local JAX devices and the iterations run
under ``jax.pmap`` with averaged gradients (data parallel, as Brax does); multi-host runs call
``jax.distributed.initialize()`` first (``--distributed`` in train.py; not tested here).
"""

from __future__ import annotations

import dataclasses
import functools
import json
import os
import pickle
import time
from pathlib import Path as FsPath
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from mjx_pathtrack import _jax_compat, datasets, ppo, robots
from mjx_pathtrack import reward as R
from mjx_pathtrack.env import EnvConfig, PathTrackingEnv
from mjx_pathtrack.executors import MjxExecutor
from mjx_pathtrack.export import export_policy
from mjx_pathtrack.fileio import append_csv_row, atomic_write_bytes
from mjx_pathtrack.train_data import ensure_train_paths
from mjx_pathtrack.evaluation import make_evaluator, summarize

_jax_compat.install()  # brax 0.14.2 on JAX >= 0.10 (GPU images); no-op on the pinned JAX

EXECUTORS = ("kinematic", "mjx")
#: task variants (``TrainConfig.task``): plain path tracking or a sensory-feedback task (mjx_pathtrack.tasks)
TASKS = ("tracking", "ball_on_plate", "balance")
#: per-path-joint deviation weights of the papers' nets (docs/method.md §2.5)
_IIWA_W = (1.0, 1.0, 1.0, 0.9, 0.8, 0.7, 0.6)
_ARMAR4_W = (1.0, 1.0) + 2 * (1.0, 1.0, 1.0, 1.0, 0.9, 0.8, 0.7, 0.6)
DEVIATION_WEIGHTS = {"iiwa": _IIWA_W, "iiwa_ball": _IIWA_W,
                     "armar6": (1.0,) + 2 * (0.95, 0.95, 0.95, 0.95, 0.9, 0.8, 0.7, 0.6),
                     "armar4": _ARMAR4_W, "armar4_legs": _ARMAR4_W}


@dataclasses.dataclass(frozen=True)
class TrainConfig:
    """Everything that defines a training run (saved as ``config.json`` in the run directory).

    The PPO settings are tuned for Brax on a CPU budget (the papers' RLlib settings in
    docs/training.md §1 use 300k-sample batches and lr 5e-5 over days); networks are the papers'
    separate 256-128 policy and value MLPs with swish activations.
    """

    robot: str = "iiwa"
    dataset: str = "random"
    dataset_root: str | None = None
    executor: str = "kinematic"
    dt: float = 0.1
    n_next: int = 8
    #: observation of the next knots: "relative" (knot - position, env.EnvConfig.knots_frame; our
    #: default: PPO learns far faster with it, docs/results.md "Findings of earlier recipes") or "absolute"
    #: (the papers' layout, docs/method.md §4)
    knots_frame: str = "relative"
    #: weight of R_l; 3 (the papers' iiwa nets: 2) makes the deterministic policy faster at the
    #: same budget (docs/results.md "Learning recipe": ratio to TOPP-RA 1.47 against 1.54 at 2)
    alpha: float = 3.0
    beta: float = 0.9
    deviation_threshold: float = 0.25
    terminate_deviation: float = 0.25
    #: [rad] the end counts as reached this arc length before it (env.EnvConfig.end_tolerance)
    end_tolerance: float = 0.0
    #: when braking at the end starts: "predictive" (env.EnvConfig.end_braking: the robot stops at
    #: the end knot instead of overshooting it by its braking distance, docs/results.md "Learning
    #: recipe") or "at_end" (the papers' rule)
    end_braking: str = "predictive"
    action_reward: float = 0.4
    duration: float = 16.0
    num_envs: int = 256
    num_timesteps: int = 9_600_000
    learning_rate: float = 3e-4
    #: None: a constant learning rate; a number: geometric from ``learning_rate`` at the start to
    #: this value at the end of training (ppo.learning_rate_scale): with the shrinking std the
    #: updates would otherwise grow (KL ~ 1/std**2) and break the policy late in training
    final_learning_rate: float | None = 3e-5
    entropy_cost: float = 1e-3
    discounting: float = 0.99
    gae_lambda: float = 0.95
    clipping_epsilon: float = 0.2
    unroll_length: int = 20
    batch_size: int = 256
    num_minibatches: int = 8
    num_updates_per_batch: int = 4
    num_evals: int = 7
    eval_episodes: int = 128
    policy_layers: tuple[int, ...] = (256, 128)
    value_layers: tuple[int, ...] = (256, 128)
    init_noise_std: float = 0.5
    #: None: the policy's log-std is learned (Brax); a number: the std is not learned but set by a
    #: schedule, geometric from ``init_noise_std`` at the start to this value at the end of
    #: training, so that the sampled policy PPO optimises converges to the deterministic one
    final_noise_std: float | None = 0.05
    mean_init_scale: float = 0.01
    #: bound of the policy mean, ``mean_clip * x / (1 + |x|)`` (Brax's ``mean_clip_scale``), like the
    #: papers' tanh mean head (docs/training.md §1); None: an unbounded mean
    mean_clip: float | None = None
    seed: int = 0
    #: the value network also sees what the return depends on but the policy's observation does
    #: not show: the steps left in the time budget, the path length left, braking
    #: (env.PathTrackingEnv.critic_features; training only: the policy and its export are unchanged).
    #: The stop reward is multiplied by the steps left in the budget; a critic that sees them learns
    #: far cleaner advantages (docs/results.md "Learning recipe"; off: the papers' value network)
    privileged_critic: bool = True
    task: str = "tracking"
    ball_reward: float = 1.0  # ball_on_plate: weight of R_ball; 0 = trained without the ball (no sensor)
    #: regenerate the train split with this many paths (deterministic, into <run>/data) when the
    #: dataset's has fewer; 0 = train on the split as it is (mjx_pathtrack.train_data)
    num_train_paths: int = 0
    legs: str = "fixed"  # balance: "fixed" (18 actions) or "controlled" (30)
    balance_reward: float = 1.0  # balance: scale of the papers' balance terms; 0 = without them

    def env_config(self) -> EnvConfig:
        weights = R.RewardWeights(alpha=self.alpha, max_deviation=self.beta, mean_deviation=self.beta,
                                  deviation_threshold=self.deviation_threshold, action=self.action_reward)
        if self.task == "balance":
            from mjx_pathtrack.tasks import humanoid_balance

            weights = humanoid_balance.balance_weights(self.balance_reward, weights)
        return EnvConfig(dt=self.dt, n_next=self.n_next, knots_frame=self.knots_frame, end_tolerance=self.end_tolerance,
                         end_braking=self.end_braking,
                         duration=self.duration,
                         terminate_deviation=self.terminate_deviation,
                         deviation_weights=DEVIATION_WEIGHTS.get(self.robot),
                         reward=weights)

    @classmethod
    def from_json(cls, text: str) -> "TrainConfig":
        data = json.loads(text)
        # runs saved before the option existed observed absolute knots (the default since is relative)
        data.setdefault("knots_frame", "absolute")
        # ... and learned their policy std (the default since is a schedule)
        data.setdefault("final_noise_std", None)
        # ... and, before these options existed, braked at the end, kept the learning rate and had
        # a value network that saw the policy's observation only
        data.setdefault("end_braking", "at_end")
        data.setdefault("final_learning_rate", None)
        data.setdefault("privileged_critic", False)
        for key in ("policy_layers", "value_layers"):
            if key in data:
                data[key] = tuple(data[key])
        unknown = set(data) - {f.name for f in dataclasses.fields(cls)}
        if unknown:
            raise ValueError(f"unknown config keys: {sorted(unknown)}")
        return cls(**data)


#: the papers' settings (docs/method.md §2.4, §3, docs/training.md §1) that ``train.py`` applies as flag defaults
#: for a robot / task; explicit flags still override them
PRESETS = {
    # + this package's budget for ARMAR-6: 60 regenerated train paths (the 5 committed ones
    # overfit: 76 % end reached on the test paths after 9.6 M steps) and 24 M steps (~25 min on 2
    # cores): 96.5 % end reached, 0.114 rad (docs/results.md "ARMAR-6 with the recipe")
    "armar6": dict(robot="armar6", dataset="random", executor="kinematic", alpha=1.0, action_reward=0.0,
                   duration=20.0, n_next=8, num_train_paths=60, num_timesteps=24_000_000, num_evals=9),
    "armar4": dict(robot="armar4", dataset="random", executor="kinematic", alpha=1.0, action_reward=0.0,
                   duration=20.0, n_next=8),
    "balance": dict(robot="armar4", dataset="random", executor="mjx", alpha=2.0, action_reward=0.0,
                    duration=20.0, n_next=8, balance_reward=1.0),
}


#: training recipes at larger budgets (``train.py --preset NAME``), flag defaults applied on top
#: of the robot/task presets (explicit flags still win); any robot or dataset (docs/results.md "Learning recipe")
RECIPES = {
    # the default recipe at 40 M steps (docs/results.md "Learning recipe")
    "paper": dict(num_timesteps=40_000_000, num_evals=11),
}
#: per (recipe, robot, dataset), settings on top of :data:`RECIPES` where they were measured
#: (they win over the robot's preset; another robot, dataset or task does not get them)
ROBOT_RECIPES = {
    # the papers' alpha 2 and 1000 train paths regenerated from the dataset's recipe (the papers'
    # count; 5 min) instead of the 200 committed: 99.5 % end reached, 1.153x TOPP-RA, 0.077 /
    # 0.099 rad after 17 min of training on 2 CPU cores (alpha 3 on the 200: 97.5 %, 1.108x,
    # 0.090 / 0.111 rad; docs/results.md "Learning recipe")
    ("paper", "iiwa", "random"): dict(alpha=2.0, num_train_paths=1000),
}


def recipe(name: str | None, robot: str = "iiwa", dataset: str = "random") -> dict[str, Any]:
    """Flag defaults of the training recipe ``name`` (None: none) for ``robot`` on ``dataset``."""
    if name is None:
        return {}
    if name not in RECIPES:
        raise ValueError(f"unknown preset {name!r}; known: {', '.join(sorted(RECIPES))}")
    return {**RECIPES[name], **ROBOT_RECIPES.get((name, robot, dataset), {})}


def preset(robot: str | None = None, task: str | None = None) -> dict[str, Any]:
    """Flag defaults of the papers' settings for ``task`` (if it has a preset) or else ``robot``."""
    if task is not None and task not in TASKS:
        raise ValueError(f"unknown task {task!r}; known: {', '.join(TASKS)}")
    return dict(PRESETS.get(task) or PRESETS.get(robot) or {})


def make_env(config: TrainConfig, split: str = "train", root=None) -> PathTrackingEnv:
    """The environment over one dataset split (``train`` or ``test``) of a registry robot
    (dataset under ``root``, default ``config.dataset_root``)."""
    if config.task not in TASKS:
        raise ValueError(f"unknown task {config.task!r}; known: {', '.join(TASKS)}")
    if config.task == "balance":
        from mjx_pathtrack.tasks import humanoid_balance

        return humanoid_balance.make_env(config, split)
    if config.task == "ball_on_plate":
        from mjx_pathtrack.tasks.ball_on_plate import from_train_config

        return from_train_config(config, split, evaluation=split == "test")
    root = config.dataset_root if root is None else root
    robot = robots.load_robot(config.robot, dt=config.dt)
    meta = datasets.read_config(config.robot, config.dataset, root)
    paths = datasets.load_paths(config.robot, config.dataset, split, root=root)
    path_joints = np.flatnonzero(np.asarray(robot.path_mask))
    if config.executor not in EXECUTORS:
        raise ValueError(f"unknown executor {config.executor!r}; known: {', '.join(EXECUTORS)}")
    executor = MjxExecutor(robot) if config.executor == "mjx" else None
    return PathTrackingEnv(robot.limits, paths, float(meta["max_dis_between_knots"]), config.env_config(),
                           path_joints=path_joints, home=robot.q0, executor=executor)


class Progress:
    """Prints env-steps/s, ETA and the latest evaluation; appends rows to ``progress.csv`` and
    writes the same scalars as TensorBoard events to ``run_dir/tensorboard``.

    Each row has ``wall_s`` (seconds of training so far: since this object was made, plus
    ``wall_offset`` for a resumed run), ``env_steps_per_s`` over the interval since the previous
    row (the first interval includes compilation) and the metrics passed in (``training/*``,
    this package's deterministic ``eval/*`` and sampled ``eval_sampled/*`` summaries)."""

    def __init__(self, run_dir: FsPath, total_steps: int, start_step: int = 0, echo: bool = True,
                 wall_offset: float = 0.0):
        from tensorboardX import SummaryWriter

        self.file = run_dir / "progress.csv"
        self.board = SummaryWriter(str(run_dir / "tensorboard"))
        self.echo = echo
        self.total = total_steps
        self.start = time.monotonic() - wall_offset
        self.last: tuple[int, float] | None = None
        self.start_step = start_step

    def wall(self) -> float:
        """Seconds of training so far (including those before a resume)."""
        return time.monotonic() - self.start

    def __call__(self, step: int, metrics: dict[str, Any]) -> None:
        step += self.start_step
        now = time.monotonic()
        rate = float("nan")
        if self.last is not None and step > self.last[0]:
            rate = (step - self.last[0]) / max(now - self.last[1], 1e-9)
        self.last = (step, now)
        eta = max(self.total - step, 0) / rate if rate == rate and rate > 0 else float("nan")
        row = {"step": step, "wall_s": now - self.start, "env_steps_per_s": rate, "eta_s": eta,
               **{k: float(np.asarray(v)) for k, v in metrics.items() if np.ndim(v) == 0}}
        append_csv_row(self.file, row)
        for key, value in row.items():
            if key != "step" and np.isfinite(value):
                self.board.add_scalar(key, value, step)
        self.board.flush()
        if self.echo:
            ret = row.get("eval/return", row.get("eval/episode_reward", float("nan")))
            line = f"step {step:>10,}  {rate:10,.0f} env-steps/s  ETA {eta / 60:6.1f} min  eval return {ret:8.2f}"
            for prefix, label in (("eval", "deterministic"), ("eval_sampled", "sampled")):
                if f"{prefix}/end_reached" in row:
                    line += (f"  {label}: end {100 * row[f'{prefix}/end_reached']:5.1f} %"
                             f" dev {row[f'{prefix}/mean_deviation']:.3f}"
                             + (f" x{row[f'{prefix}/ratio_to_toppra']:.2f}" if f"{prefix}/ratio_to_toppra" in row else ""))
            print(line, flush=True)


def truncate_progress(file: FsPath, after_step: int) -> None:
    """Drop the rows of ``progress.csv`` logged after ``after_step`` (a resumed run logs them again)."""
    import csv
    import io

    if not file.is_file():
        return
    with open(file, newline="") as f:
        reader = csv.DictReader(f)
        fields, rows = reader.fieldnames or [], [r for r in reader if float(r["step"]) <= after_step]
    text = io.StringIO()
    writer = csv.DictWriter(text, fieldnames=fields, restval="")
    writer.writeheader()
    writer.writerows(rows)
    atomic_write_bytes(file, text.getvalue().encode())


#: Brax PPO network factory of a config (kept here under its old name)
ppo_networks = ppo.networks


class ConfigError(ValueError):
    """A training option that cannot work; the message names the option and the allowed values."""


class RunDirError(ValueError):
    """The run directory cannot be used as asked (holds another run, is a file, not writable)."""


class TrainingDiverged(RuntimeError):
    """Training produced non-finite parameters or losses; the last good checkpoint is kept."""


def validate_config(config: TrainConfig, devices: int = 1) -> None:
    """Raise :class:`ConfigError` naming the option unless every option of ``config`` can work:
    before anything is written or compiled."""
    c = config

    def fail(option, message):
        raise ConfigError(f"--{option.replace('_', '-')}: {message}")

    choices = {"executor": EXECUTORS, "task": TASKS}
    from mjx_pathtrack.env import END_BRAKING, KNOTS_FRAMES

    choices["knots_frame"] = KNOTS_FRAMES
    choices["end_braking"] = END_BRAKING
    for name, allowed in choices.items():
        if getattr(c, name) not in allowed:
            fail(name, f"{getattr(c, name)!r} is not one of {', '.join(allowed)}")
    if c.task != "balance" and c.robot not in robots.known_robots():
        fail("robot", f"unknown robot {c.robot!r}; known: {', '.join(robots.known_robots())}")
    if c.task == "balance":
        from mjx_pathtrack.tasks.humanoid_balance import LEGS

        if c.legs not in LEGS:
            fail("legs", f"{c.legs!r} is not one of {', '.join(LEGS)}")
    for name in ("dt", "duration", "learning_rate", "init_noise_std", "mean_init_scale", "deviation_threshold",
                 "terminate_deviation"):
        value = getattr(c, name)
        if not (np.isfinite(value) and value > 0):
            fail(name, f"must be a finite number > 0, got {value}")
    for name in ("alpha", "beta", "action_reward", "entropy_cost", "end_tolerance", "ball_reward", "balance_reward"):
        value = getattr(c, name)
        if not (np.isfinite(value) and value >= 0):
            fail(name, f"must be a finite number >= 0, got {value}")
    for name, lo, hi in (("discounting", 0.0, 1.0), ("gae_lambda", 0.0, 1.0), ("clipping_epsilon", 0.0, 1.0)):
        value = getattr(c, name)
        if not (np.isfinite(value) and lo < value <= hi):
            fail(name, f"must be in ({lo:g}, {hi:g}], got {value}")
    if c.final_noise_std is not None and not (np.isfinite(c.final_noise_std) and c.final_noise_std > 0):
        fail("final_noise_std", f"must be a finite number > 0 (or unset), got {c.final_noise_std}")
    if c.final_learning_rate is not None and not (np.isfinite(c.final_learning_rate) and c.final_learning_rate > 0):
        fail("final_learning_rate", f"must be a finite number > 0 (or unset), got {c.final_learning_rate}")
    if c.mean_clip is not None and not (np.isfinite(c.mean_clip) and c.mean_clip > 0):
        fail("mean_clip", f"must be a finite number > 0 (or unset), got {c.mean_clip}")
    for name in ("num_envs", "num_timesteps", "unroll_length", "batch_size", "num_minibatches",
                 "num_updates_per_batch", "num_evals", "eval_episodes", "n_next"):
        value = getattr(c, name)
        if not value >= 1:
            fail(name, f"must be >= 1, got {value}")
    if c.num_train_paths < 0:
        fail("num_train_paths", f"must be >= 0, got {c.num_train_paths}")
    for name in ("policy_layers", "value_layers"):
        if not getattr(c, name) or min(getattr(c, name)) < 1:
            fail(name, f"needs at least one layer, each of size >= 1, got {list(getattr(c, name))}")
    if c.num_envs % devices:
        fail("num_envs", f"{c.num_envs} is not a multiple of the {devices} devices it is split over")
    if (c.batch_size * c.num_minibatches) % c.num_envs:
        fail("batch_size", f"batch_size * num_minibatches ({c.batch_size} * {c.num_minibatches} = "
                           f"{c.batch_size * c.num_minibatches}) must be a multiple of --num-envs ({c.num_envs})")
    if c.executor == "mjx" or c.task in ("ball_on_plate", "balance"):
        steps = c.dt / robots.SIM_DT
        if abs(steps - round(steps)) > 1e-6:
            fail("dt", f"{c.dt} s must be a whole multiple of the physics step {robots.SIM_DT:.6g} s with MJX physics")
    if c.task == "tracking":
        try:
            datasets.read_config(c.robot, c.dataset, c.dataset_root)
        except datasets.DatasetError as e:
            known = datasets.known_kinds(c.robot, c.dataset_root)
            fail("dataset", f"{e}" + (f"; datasets of {c.robot}: {', '.join(known)}" if known else ""))


#: files and folders of a run directory that this package writes
RUN_FILES = ("config.json", "progress.csv", "checkpoints", "params.pkl", "report.json", "export", "tensorboard",
             "data", "eval")


def prepare_run_dir(run_dir: FsPath, resume: bool, overwrite: bool) -> bool:
    """Check that ``run_dir`` can take this run (nothing is written). Returns whether the
    directory holds a previous run. Raises :class:`RunDirError`: a file, not writable, or a run
    that neither ``resume`` nor ``overwrite`` was asked for."""
    if run_dir.exists() and not run_dir.is_dir():
        raise RunDirError(f"--out {run_dir}: is a file, not a directory")
    parent = next((p for p in [run_dir, *run_dir.parents] if p.exists()), None)
    if parent is None or not parent.is_dir() or not os.access(parent, os.W_OK | os.X_OK):
        raise RunDirError(f"--out {run_dir}: cannot create or write it ({parent} is not a writable directory)")
    held = [name for name in RUN_FILES if (run_dir / name).exists()]
    if held and not (resume or overwrite):
        raise RunDirError(f"--out {run_dir}: holds a training run ({', '.join(held)}); use --resume to continue it, "
                          f"--overwrite to replace it, or choose another --out")
    if resume and overwrite:
        raise RunDirError("--resume and --overwrite exclude each other")
    return bool(held)


def clear_run_dir(run_dir: FsPath) -> None:
    """Remove what this package wrote into ``run_dir`` (``--overwrite``)."""
    import shutil

    for name in RUN_FILES:
        target = run_dir / name
        if target.is_dir():
            shutil.rmtree(target)
        elif target.exists():
            target.unlink()


# ---------------------------------------------------------------------------------------------
# Checkpoints: the whole learner state after each evaluation interval
# ---------------------------------------------------------------------------------------------

CHECKPOINT_FORMAT = 1
CHECKPOINT_SUFFIX = ".ckpt"
#: checkpoints kept per run (older ones are deleted)
KEEP_CHECKPOINTS = 3


def checkpoint_path(checkpoints: FsPath, step: int) -> FsPath:
    return checkpoints / f"{step:012d}{CHECKPOINT_SUFFIX}"


def latest_checkpoint(checkpoints: FsPath) -> tuple[FsPath, int] | None:
    """The newest checkpoint file and the env steps it stands for, or None. Files are written
    atomically, so any file found is complete."""
    if not checkpoints.is_dir():
        return None
    found = [(int(f.name[:-len(CHECKPOINT_SUFFIX)]), f) for f in checkpoints.iterdir()
             if f.name.endswith(CHECKPOINT_SUFFIX) and f.name[:-len(CHECKPOINT_SUFFIX)].isdigit()]
    if not found:
        return None
    step, path = max(found)
    return path, step


def save_checkpoint(checkpoints: FsPath, step: int, state: dict) -> FsPath:
    """Write ``state`` (host arrays) as the checkpoint of ``step``; keep the newest few."""
    path = checkpoint_path(checkpoints, step)
    atomic_write_bytes(path, pickle.dumps({"format": CHECKPOINT_FORMAT, "step": step, **state}))
    old = sorted(f for f in checkpoints.iterdir() if f.name.endswith(CHECKPOINT_SUFFIX))
    for f in old[:-KEEP_CHECKPOINTS]:
        f.unlink()
    return path


def load_checkpoint(path: FsPath) -> dict:
    data = pickle.loads(path.read_bytes())
    if not isinstance(data, dict) or data.get("format") != CHECKPOINT_FORMAT:
        raise RunDirError(f"{path}: not a checkpoint of this package's format {CHECKPOINT_FORMAT} "
                          f"(a run from before exact resume? train it again with --overwrite)")
    return data


# ---------------------------------------------------------------------------------------------
# Training
# ---------------------------------------------------------------------------------------------


class _Program(NamedTuple):
    core: Any
    init: Any  # (seed) -> Learner (with a leading device axis when pmapped)
    epoch: Any  # (Learner, start, end) -> (Learner, summary); start, end: fractions of the budget
    devices: int
    iterations: int  # training iterations per evaluation interval
    epochs: int


def _program(config: TrainConfig, env: PathTrackingEnv) -> _Program:
    """The compiled training program: one evaluation interval per call, over the local devices."""
    c = config
    devices = jax.local_device_count()
    processes = jax.process_count()
    if c.num_envs % (devices * processes):
        devices = 1 if c.num_envs % processes == 0 else devices
    axis = ppo.DEVICE_AXIS if devices > 1 else None
    core = ppo.build(c, env, axis_name=axis)
    weights = ppo.reward_weights(c)
    epochs = max(c.num_evals - 1, 1)
    iterations = max(int(np.ceil(c.num_timesteps / (epochs * core.steps_per_iteration))), 1)
    envs_per_device = c.num_envs // (devices * processes)

    def step(learner, fraction):
        return ppo.scheduled_iteration(core, weights, learner, fraction)

    if devices == 1:
        def init(seed):
            return jax.jit(lambda: core.init(seed, weights, envs_per_device, jax.process_index()))()

        return _Program(core, init, ppo.make_epoch(jax.jit(step, donate_argnums=(0,)), iterations), 1, iterations,
                        epochs)

    first = jax.process_index() * devices

    def init(seed):
        return jax.pmap(lambda d: core.init(seed, weights, envs_per_device, d), axis_name=axis)(
            first + jnp.arange(devices))

    pmapped = jax.pmap(step, axis_name=axis, in_axes=(0, None), donate_argnums=(0,))
    return _Program(core, init, ppo.make_epoch(pmapped, iterations), devices, iterations, epochs)


def _eval_baseline(env: PathTrackingEnv, key, episodes: int) -> np.ndarray:
    """TOPP-RA durations of the evaluation episodes (the same every evaluation: a fixed key), so
    that progress.csv shows the policy/TOPP-RA ratio."""
    from mjx_pathtrack import baseline
    from mjx_pathtrack.evaluation import episode_references

    paths, s_start = episode_references(env, key, episodes)
    pj = np.asarray(env.path_joints)
    return baseline.baseline_durations(paths, s_start, np.asarray(env.limits.vel)[pj], np.asarray(env.limits.acc)[pj])


def _host(tree):
    return jax.tree.map(np.asarray, jax.device_get(tree))


def _brax_params(learner, devices: int):
    """``(normalizer, policy, value)`` host arrays of a learner (device 0's copy)."""
    params = (learner.normalizer_params, learner.params.policy, learner.params.value)
    params = _host(params)
    return jax.tree.map(lambda x: x[0], params) if devices > 1 else params


def train(config: TrainConfig, run_dir: str | os.PathLike, resume: bool = False, verbose: bool = True,
          overwrite: bool = False):
    """Train; returns ``(make_inference_fn, params, report)`` where ``report`` holds the
    evaluation summaries before and after training on the test split (deterministic policy:
    ``before``/``after``; sampled: ``before_sampled``/``after_sampled``). The run directory gets
    ``config.json``, ``progress.csv``, ``checkpoints/`` (the whole learner state after every
    evaluation interval), ``params.pkl``, ``report.json`` and the jitted policy export
    ``export/`` (:mod:`mjx_pathtrack.export`).

    Every option is validated and the run directory checked before anything is written: a
    directory that holds a run is only continued with ``resume`` (the saved config must be
    equal) or replaced with ``overwrite``. ``resume`` continues exactly: the final parameters
    equal those of an uninterrupted run. Non-finite parameters or losses stop the run with
    :class:`TrainingDiverged`; the last good checkpoint stays."""
    run_dir = FsPath(run_dir)
    validate_config(config)
    held = prepare_run_dir(run_dir, resume, overwrite)
    config_file = run_dir / "config.json"
    if resume and config_file.exists():
        saved = TrainConfig.from_json(config_file.read_text())
        if saved != config:
            changed = [f.name for f in dataclasses.fields(TrainConfig) if getattr(saved, f.name) != getattr(config, f.name)]
            raise ValueError(f"--resume: config differs from the saved one in {config_file} ({', '.join(changed)})")
    latest = latest_checkpoint(run_dir / "checkpoints") if resume else None
    checkpoint = load_checkpoint(latest[0]) if latest else None
    created = not run_dir.exists()
    try:
        if overwrite and held:
            clear_run_dir(run_dir)
        run_dir.mkdir(parents=True, exist_ok=True)
        atomic_write_bytes(config_file, (json.dumps(dataclasses.asdict(config), indent=2) + "\n").encode())
        return _train(config, run_dir, checkpoint, verbose)
    except BaseException:
        if created and latest_checkpoint(run_dir / "checkpoints") is None:
            import shutil

            shutil.rmtree(run_dir, ignore_errors=True)  # nothing trained yet: leave nothing behind
        raise


def _train(config: TrainConfig, run_dir: FsPath, checkpoint: dict | None, verbose: bool):
    root = ensure_train_paths(config.robot, config.dataset, config.num_train_paths, config.dataset_root,
                              run_dir / "data", log=print if verbose else None)
    env, test_env = make_env(config, "train", root), make_env(config, "test", root)
    program = _program(config, env)
    core = program.core
    steps_per_epoch = program.iterations * core.steps_per_iteration
    total = program.epochs * steps_per_epoch
    evaluator = make_evaluator(test_env, core.make_policy, config.eval_episodes, deterministic=None)
    eval_key = jax.random.PRNGKey(config.seed + 1)
    toppra = _eval_baseline(test_env, eval_key, config.eval_episodes)

    def evaluation(learner) -> dict[str, float]:
        params = _brax_params(learner, program.devices)
        out = {}
        for sampled, prefix in ((False, "eval"), (True, "eval_sampled")):
            for k, v in summarize(evaluator(params, eval_key, sampled), toppra).items():
                out[f"{prefix}/{k}"] = v
        return out

    checkpoints = run_dir / "checkpoints"
    if checkpoint is None:
        learner, start_step, wall, evals = program.init(config.seed), 0, 0.0, {}
        truncate_progress(run_dir / "progress.csv", -1)
    else:
        if int(checkpoint["devices"]) != program.devices:
            raise RunDirError(f"{checkpoints}: written by a run on {checkpoint['devices']} devices, this one has "
                              f"{program.devices}; resume on the same number of devices")
        learner = jax.tree.map(jnp.asarray, checkpoint["learner"])
        start_step, wall, evals = int(checkpoint["step"]), float(checkpoint["wall_s"]), checkpoint["evaluations"]
        truncate_progress(run_dir / "progress.csv", int(checkpoint["step"]))
        if verbose:
            print(f"resuming from {checkpoints.name}/{checkpoint_path(checkpoints, checkpoint['step']).name} "
                  f"({checkpoint['step']:,} of {total:,} steps done, {wall / 60:.1f} min)", flush=True)
    progress = Progress(run_dir, total, 0, echo=verbose, wall_offset=wall)
    if checkpoint is not None:  # the first interval's rate then includes the compilation, as in a new run
        progress.last = (int(checkpoint["step"]), time.monotonic())
    if checkpoint is None:
        evals["before"] = evaluation(learner)
        if verbose:
            print("evaluation before training:", _fmt(_unprefix(evals["before"], "eval")), flush=True)
        progress(0, evals["before"])
    latest = evals.get("latest", evals["before"])
    # intervals of steps_per_epoch until the budget is used (a resumed run whose config.json was
    # edited to a larger num_timesteps goes on with intervals of the new size)
    step = start_step
    while step < total:
        learner, summary = program.epoch(learner, np.float32(step / total), np.float32((step + steps_per_epoch) / total))
        summary = _host(summary)
        if program.devices > 1:
            summary = jax.tree.map(lambda x: x[0], summary)
        step += steps_per_epoch
        finite = bool(ppo.all_finite((learner.params, learner.normalizer_params))) and \
            all(np.isfinite(v) for v in summary.values())
        if not finite:
            last = latest_checkpoint(checkpoints)
            raise TrainingDiverged(
                f"training diverged between steps {step - steps_per_epoch:,} and {step:,}: non-finite parameters or "
                f"losses (try a lower --learning-rate); the last good checkpoint is "
                f"{last[0] if last else 'none (diverged in the first interval)'}")
        latest = evaluation(learner)
        metrics = {**{f"training/{k}": v for k, v in summary.items()}, **latest}
        progress(step, metrics)
        _fault_injection(step)
        evals["latest"] = latest
        save_checkpoint(checkpoints, step, {"wall_s": progress.wall(), "devices": program.devices,
                                            "learner": _host(learner), "evaluations": evals})
    params = _brax_params(learner, program.devices)
    report = {"before": _unprefix(evals["before"], "eval"), "after": _unprefix(latest, "eval"),
              "before_sampled": _unprefix(evals["before"], "eval_sampled"),
              "after_sampled": _unprefix(latest, "eval_sampled")}
    if verbose:
        print("evaluation after training:  ", _fmt(report["after"]), flush=True)
        print("  sampled actions:          ", _fmt(report["after_sampled"]), flush=True)
    joint_names = getattr(test_env, "joint_names", None) or robots.load_robot(config.robot, dt=config.dt).joint_names
    write_results(run_dir, core.make_policy, params, test_env, config.robot, joint_names, report)
    return core.make_policy, params, report


#: testing aid: a process whose environment sets this to N kills itself with SIGKILL once it has
#: logged the progress of step >= N and before that step's checkpoint is written (the worst
#: moment for a resume: the log is ahead of the last checkpoint)
KILL_VAR = "MJX_PATHTRACK_KILL_AT_STEP"


def _fault_injection(step: int) -> None:
    at = os.environ.get(KILL_VAR)
    if at is not None and step >= int(at):
        import signal

        os.kill(os.getpid(), signal.SIGKILL)


def write_results(run_dir: FsPath, make_policy, params, env, robot: str, joint_names, report: dict) -> None:
    """``params.pkl``, ``export/`` and ``report.json`` of a finished run, written side by side
    first and then moved into place (a kill leaves the previous set or the new one, each file
    whole; the export directory is swapped as a whole)."""
    import shutil

    staging = run_dir / ".results.tmp"
    shutil.rmtree(staging, ignore_errors=True)
    staging.mkdir()
    atomic_write_bytes(staging / "params.pkl", pickle.dumps(params))
    export_policy(staging / "export", make_policy, params, env, robot, joint_names)
    atomic_write_bytes(staging / "report.json", (json.dumps(json_safe(report), indent=2) + "\n").encode())
    old_export = run_dir / ".export.old"
    shutil.rmtree(old_export, ignore_errors=True)
    if (run_dir / "export").exists():
        os.replace(run_dir / "export", old_export)
    os.replace(staging / "export", run_dir / "export")
    os.replace(staging / "params.pkl", run_dir / "params.pkl")
    os.replace(staging / "report.json", run_dir / "report.json")
    shutil.rmtree(old_export, ignore_errors=True)
    staging.rmdir()


def _unprefix(metrics: dict[str, float], prefix: str) -> dict[str, float]:
    return {k[len(prefix) + 1:]: v for k, v in metrics.items() if k.startswith(prefix + "/")}


def json_safe(value):
    """``value`` with NaN/inf floats replaced by None (strict JSON)."""
    if isinstance(value, dict):
        return {k: json_safe(v) for k, v in value.items()}
    if isinstance(value, float) and not np.isfinite(value):
        return None
    return value


def _fmt(summary: dict[str, float]) -> str:
    return "  ".join(f"{k}={v:.3f}" for k, v in summary.items())
