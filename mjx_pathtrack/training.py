"""Brax PPO training of the path-tracking policy: config, environment wiring, progress, logs,
checkpoints and resume. ``train.py`` at the repository root is the command-line front end.

Multi-device: Brax PPO shards the environments over every local JAX device (``jax.pmap``);
multi-host runs call ``jax.distributed.initialize()`` first (``--distributed`` in train.py), after
which Brax uses the devices of every process. Nothing here is device specific.
"""

from __future__ import annotations

import dataclasses
import functools
import json
import os
import pickle
import time
from pathlib import Path as FsPath
from typing import Any

import jax
import numpy as np

from mjx_pathtrack import _jax_compat, datasets, robots
from mjx_pathtrack import reward as R
from mjx_pathtrack.env import EnvConfig, PathTrackingEnv
from mjx_pathtrack.executors import MjxExecutor
from mjx_pathtrack.export import export_policy
from mjx_pathtrack.fileio import append_csv_row, atomic_write_bytes
from mjx_pathtrack.train_data import ensure_train_paths
from mjx_pathtrack.evaluation import make_evaluator, summarize
from mjx_pathtrack.wrappers import wrap_for_training

_jax_compat.install()  # brax 0.14.2 on JAX >= 0.10 (GPU images); no-op on the pinned JAX

EXECUTORS = ("kinematic", "mjx")
#: task variants (``TrainConfig.task``): plain path tracking or a sensory-feedback task (mjx_pathtrack.tasks)
TASKS = ("tracking", "ball_on_plate", "balance")
#: per-path-joint deviation weights of the papers' nets (REFERENCE §1.5)
_IIWA_W = (1.0, 1.0, 1.0, 0.9, 0.8, 0.7, 0.6)
_ARMAR4_W = (1.0, 1.0) + 2 * (1.0, 1.0, 1.0, 1.0, 0.9, 0.8, 0.7, 0.6)
DEVIATION_WEIGHTS = {"iiwa": _IIWA_W, "iiwa_ball": _IIWA_W,
                     "armar6": (1.0,) + 2 * (0.95, 0.95, 0.95, 0.95, 0.9, 0.8, 0.7, 0.6),
                     "armar4": _ARMAR4_W, "armar4_legs": _ARMAR4_W}


@dataclasses.dataclass(frozen=True)
class TrainConfig:
    """Everything that defines a training run (saved as ``config.json`` in the run directory).

    The PPO settings are tuned for Brax on a CPU budget (the papers' RLlib settings in
    REFERENCE §6.1 use 300k-sample batches and lr 5e-5 over days); networks are the papers'
    separate 256-128 policy and value MLPs with swish activations.
    """

    robot: str = "iiwa"
    dataset: str = "random"
    dataset_root: str | None = None
    executor: str = "kinematic"
    dt: float = 0.1
    n_next: int = 8
    #: observation of the next knots: "relative" (knot - position, env.EnvConfig.knots_frame; our
    #: default: PPO learns far faster with it, README "Environment and training") or "absolute"
    #: (the papers' layout, REFERENCE §2)
    knots_frame: str = "relative"
    alpha: float = 2.0
    beta: float = 0.9
    deviation_threshold: float = 0.25
    terminate_deviation: float = 0.25
    #: [rad] the end counts as reached this arc length before it (env.EnvConfig.end_tolerance)
    end_tolerance: float = 0.0
    action_reward: float = 0.4
    duration: float = 16.0
    num_envs: int = 256
    num_timesteps: int = 8_000_000
    learning_rate: float = 3e-4
    entropy_cost: float = 1e-3
    discounting: float = 0.99
    gae_lambda: float = 0.95
    clipping_epsilon: float = 0.2
    unroll_length: int = 20
    batch_size: int = 256
    num_minibatches: int = 8
    num_updates_per_batch: int = 4
    num_evals: int = 6
    eval_episodes: int = 128
    policy_layers: tuple[int, ...] = (256, 128)
    value_layers: tuple[int, ...] = (256, 128)
    init_noise_std: float = 0.5
    mean_init_scale: float = 0.01
    #: bound of the policy mean, ``mean_clip * x / (1 + |x|)`` (Brax's ``mean_clip_scale``), like the
    #: papers' tanh mean head (REFERENCE §6.1); None: an unbounded mean
    mean_clip: float | None = None
    seed: int = 0
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
                         duration=self.duration,
                         terminate_deviation=self.terminate_deviation,
                         deviation_weights=DEVIATION_WEIGHTS.get(self.robot),
                         reward=weights)

    @classmethod
    def from_json(cls, text: str) -> "TrainConfig":
        data = json.loads(text)
        # runs saved before the option existed observed absolute knots (the default since is relative)
        data.setdefault("knots_frame", "absolute")
        for key in ("policy_layers", "value_layers"):
            if key in data:
                data[key] = tuple(data[key])
        unknown = set(data) - {f.name for f in dataclasses.fields(cls)}
        if unknown:
            raise ValueError(f"unknown config keys: {sorted(unknown)}")
        return cls(**data)


#: the papers' settings (REFERENCE §1.4, §1.6, §6.1) that ``train.py`` applies as flag defaults
#: for a robot / task; explicit flags still override them
PRESETS = {
    "armar6": dict(robot="armar6", dataset="random", executor="kinematic", alpha=1.0, action_reward=0.0,
                   duration=20.0, n_next=8),
    "armar4": dict(robot="armar4", dataset="random", executor="kinematic", alpha=1.0, action_reward=0.0,
                   duration=20.0, n_next=8),
    "balance": dict(robot="armar4", dataset="random", executor="mjx", alpha=2.0, action_reward=0.0,
                    duration=20.0, n_next=8, balance_reward=1.0),
}


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

    Each row has ``wall_s`` (seconds since this object was made), ``env_steps_per_s`` over the
    interval since the previous row (the first interval includes compilation) and the metrics
    passed in (Brax's ``training/*`` and this package's ``eval/*`` summaries)."""

    def __init__(self, run_dir: FsPath, total_steps: int, start_step: int = 0, echo: bool = True):
        from tensorboardX import SummaryWriter

        self.file = run_dir / "progress.csv"
        self.board = SummaryWriter(str(run_dir / "tensorboard"))
        self.echo = echo
        self.total = total_steps
        self.start = time.monotonic()
        self.last: tuple[int, float] | None = None
        self.start_step = start_step

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
            if "eval/end_reached" in row:
                line += f"  end reached {100 * row['eval/end_reached']:5.1f} %  deviation {row['eval/mean_deviation']:.3f} rad"
            print(line, flush=True)


def ppo_networks(config: TrainConfig):
    from brax.training.agents.ppo import networks as ppo_networks_module

    # As in the papers (REFERENCE §6.1): a Gaussian policy whose samples the environment clips
    # to [-1, 1], a learned state-independent log-std, and a mean head initialised near zero
    # (normc(0.01) there) so that the initial mean action is ~0, the middle of every safe range:
    # the robot starts by barely moving instead of leaving the path within a few steps.
    return functools.partial(ppo_networks_module.make_ppo_networks,
                             policy_hidden_layer_sizes=config.policy_layers,
                             value_hidden_layer_sizes=config.value_layers,
                             distribution_type="normal", noise_std_type="log",
                             init_noise_std=config.init_noise_std,
                             mean_clip_scale=config.mean_clip,
                             mean_kernel_init_fn=jax.nn.initializers.variance_scaling,
                             mean_kernel_init_kwargs=dict(scale=config.mean_init_scale ** 2, mode="fan_in",
                                                          distribution="truncated_normal"))


def train(config: TrainConfig, run_dir: str | os.PathLike, resume: bool = False, verbose: bool = True):
    """Train; returns ``(make_inference_fn, params, report)`` where ``report`` holds the
    evaluation summaries before and after training on the test split. The run directory gets
    ``config.json``, ``progress.csv``, ``checkpoints/``, ``params.pkl``, ``report.json`` and the
    jitted policy export ``export/`` (:mod:`mjx_pathtrack.export`)."""
    from brax.training.agents.ppo import train as ppo

    run_dir = FsPath(run_dir)
    run_dir.mkdir(parents=True, exist_ok=True)
    config_file = run_dir / "config.json"
    if resume and config_file.exists():
        saved = TrainConfig.from_json(config_file.read_text())
        if saved != config:
            raise ValueError(f"--resume: config differs from the saved one in {config_file}")
    atomic_write_bytes(config_file, (json.dumps(dataclasses.asdict(config), indent=2) + "\n").encode())
    root = ensure_train_paths(config.robot, config.dataset, config.num_train_paths, config.dataset_root,
                              run_dir / "data", log=print if verbose else None)
    env, test_env = make_env(config, "train", root), make_env(config, "test", root)
    checkpoints = run_dir / "checkpoints"
    latest = latest_checkpoint(checkpoints) if resume else None
    restore, done_steps = latest if latest else (None, 0)
    if restore and verbose:
        print(f"resuming from {restore} ({done_steps:,} of {config.num_timesteps:,} steps done)", flush=True)
    episode_length = config.env_config().max_episode_steps() + 1

    report: dict[str, Any] = {}
    eval_key = jax.random.PRNGKey(config.seed + 1)

    evaluators = {}
    progress = Progress(run_dir, config.num_timesteps, done_steps, echo=verbose)
    latest: dict[str, float] = {}

    def evaluation(make_inference_fn, params) -> dict[str, float]:
        if "fn" not in evaluators:
            evaluators["fn"] = make_evaluator(test_env, make_inference_fn, config.eval_episodes)
        # host copies: parameters fresh from Brax's pmap and from its initialisation differ in
        # placement, which would compile the evaluator twice (~20 s each on CPU)
        return summarize(evaluators["fn"](jax.tree.map(np.asarray, params), eval_key))

    def policy_params_fn(step, make_inference_fn, params):
        # Brax calls this at the start and after every training iteration, before progress_fn:
        # the evaluation of this package (full test episodes, deterministic policy) replaces
        # Brax's evaluator, which would run (and compile) a second rollout per evaluation
        latest.clear()
        latest.update(evaluation(make_inference_fn, params))
        if "before" not in report:
            report["before"] = dict(latest)
            if verbose:
                print("evaluation before training:", _fmt(report["before"]), flush=True)
            progress(step, {f"eval/{k}": v for k, v in latest.items()})

    def progress_fn(step, metrics):
        progress(step, {**metrics, **{f"eval/{k}": v for k, v in latest.items()}})

    make_inference_fn, params, _ = ppo.train(
        environment=env, eval_env=test_env, wrap_env_fn=wrap_for_training,
        num_timesteps=max(config.num_timesteps - done_steps, 1), episode_length=episode_length, num_envs=config.num_envs,
        learning_rate=config.learning_rate, entropy_cost=config.entropy_cost, discounting=config.discounting,
        gae_lambda=config.gae_lambda, clipping_epsilon=config.clipping_epsilon,
        unroll_length=config.unroll_length, batch_size=config.batch_size, num_minibatches=config.num_minibatches,
        num_updates_per_batch=config.num_updates_per_batch, num_evals=config.num_evals,
        run_evals=False, num_eval_envs=1,  # Brax still builds (and resets) its unused evaluator
        normalize_observations=True,
        network_factory=ppo_networks(config), seed=config.seed,
        progress_fn=progress_fn, policy_params_fn=policy_params_fn,
        save_checkpoint_path=str((checkpoints / f"{done_steps:012d}").resolve()),
        restore_checkpoint_path=str(restore) if restore else None)
    report["after"] = dict(latest)  # Brax evaluated the final parameters last (policy_params_fn)
    if verbose:
        print("evaluation after training: ", _fmt(report["after"]), flush=True)
    atomic_write_bytes(run_dir / "params.pkl", pickle.dumps(jax.tree.map(np.asarray, params)))
    joint_names = getattr(test_env, "joint_names", None) or robots.load_robot(config.robot, dt=config.dt).joint_names
    export_policy(run_dir / "export", make_inference_fn, params, test_env, config.robot, joint_names)
    atomic_write_bytes(run_dir / "report.json", (json.dumps(json_safe(report), indent=2) + "\n").encode())
    return make_inference_fn, params, report


#: written last into a Brax PPO checkpoint directory: its presence marks a complete checkpoint
CHECKPOINT_DONE_FILE = "ppo_network_config.json"


def latest_checkpoint(checkpoints: FsPath) -> tuple[FsPath, int] | None:
    """The newest *complete* Brax checkpoint and the total env steps it stands for, or None.

    Layout: ``checkpoints/<offset>/<step>/`` -- each (re)start of a run saves under the number of
    steps done before it (Brax counts from 0 again after a restore). A directory that a kill left
    half-written (no network config yet) is ignored."""
    if not checkpoints.is_dir():
        return None
    found = [(int(o.name) + int(p.name), p) for o in checkpoints.iterdir() if o.is_dir() and o.name.isdigit()
             for p in o.iterdir() if p.is_dir() and p.name.isdigit() and (p / CHECKPOINT_DONE_FILE).is_file()]
    if not found:
        return None
    total, path = max(found, key=lambda x: x[0])
    return path, total


def json_safe(value):
    """``value`` with NaN/inf floats replaced by None (strict JSON)."""
    if isinstance(value, dict):
        return {k: json_safe(v) for k, v in value.items()}
    if isinstance(value, float) and not np.isfinite(value):
        return None
    return value


def _fmt(summary: dict[str, float]) -> str:
    return "  ".join(f"{k}={v:.3f}" for k, v in summary.items())
