"""PPO training and evaluation for the velocity-maximisation task (paper 001 Tables I and II).

    python -m mjx_pathtrack.rl.velocity_max_train train --hz 10 --mode safe --num-timesteps 300000 --out runs/velmax/safe_10
    python -m mjx_pathtrack.rl.velocity_max_train optimal                 # optimal vs random, all frequencies
    python -m mjx_pathtrack.rl.velocity_max_train optimal --search        # + the optimality check

Reuses the project's Brax PPO machinery (:func:`mjx_pathtrack.rl.training.ppo_networks`,
:class:`~mjx_pathtrack.rl.training.Progress`, :func:`~mjx_pathtrack.envs.wrappers.wrap_for_training`).
A run directory gets ``config.json``, ``progress.csv``, ``tensorboard/``, ``params.pkl`` and
``report.json`` (trained, random and optimal policy evaluated on the same episodes).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import pickle
import time
from pathlib import Path
from typing import Any

from mjx_pathtrack.fileio import atomic_write_bytes  # first: the package sets the CPU XLA flags before JAX starts
from mjx_pathtrack.envs.tasks import velocity_max as V

import jax
import numpy as np


@dataclasses.dataclass(frozen=True)
class VelocityTrainConfig:
    """A training run (saved as ``config.json``). ``horizon_s`` [s] sets the discount per step,
    ``1 - dt / horizon_s``, so that every frequency looks the same time ahead. The network and
    PPO sizes are small for a CPU budget (the task is per-joint and nearly myopic).
    ``brax_evals``: run Brax's evaluator ``num_evals`` times (the eval return in
    ``progress.csv``); off by default because its compilation costs as much as a short run on
    a shared CPU -- the final evaluation (``report.json``) is always done."""

    hz: float = 20.0
    mode: str = "safe"
    duration: float = 5.0
    init_spread: float = 0.5
    num_timesteps: int = 300_000
    num_envs: int = 64
    learning_rate: float = 1e-3
    entropy_cost: float = 1e-3
    horizon_s: float = 1.0
    gae_lambda: float = 0.95
    clipping_epsilon: float = 0.2
    unroll_length: int = 16
    batch_size: int = 64
    num_minibatches: int = 4
    num_updates_per_batch: int = 4
    num_evals: int = 4
    brax_evals: bool = False
    eval_episodes: int = 128
    policy_layers: tuple[int, ...] = (64, 64)
    value_layers: tuple[int, ...] = (64, 64)
    init_noise_std: float = 0.5
    mean_init_scale: float = 0.01
    #: bound of the policy mean (training.TrainConfig.mean_clip), like the papers' tanh mean head;
    #: without it the 120/240 Hz policies drift to means far outside [-1, 1] and stop exploring
    #: (docs/results.md "Paper 001 experiments"); ``--mean-clip none`` turns it off
    mean_clip: float | None = 1.0
    seed: int = 0

    def env_config(self) -> V.VelocityMaxConfig:
        return V.VelocityMaxConfig(hz=self.hz, mode=self.mode, duration=self.duration, init_spread=self.init_spread)

    @property
    def discounting(self) -> float:
        return max(0.0, 1.0 - 1.0 / (self.hz * self.horizon_s))


def make_env(config: VelocityTrainConfig) -> V.VelocityMaxEnv:
    return V.VelocityMaxEnv(config.env_config())


def train(config: VelocityTrainConfig, run_dir: str | Path, verbose: bool = True):
    """Train PPO; returns ``(make_inference_fn, params, report)``. ``report`` holds the
    evaluation (:func:`velocity_max.evaluate`) of the trained (deterministic), random and
    optimal policies on ``eval_episodes`` episodes and the wall time."""
    from brax.training.agents.ppo import train as ppo

    from mjx_pathtrack.rl.training import Progress, ppo_networks, json_safe
    from mjx_pathtrack.envs.wrappers import wrap_for_training

    run_dir = Path(run_dir)
    run_dir.mkdir(parents=True, exist_ok=True)
    atomic_write_bytes(run_dir / "config.json", (json.dumps(dataclasses.asdict(config), indent=2) + "\n").encode())
    progress_file = run_dir / "progress.csv"
    if progress_file.exists():
        progress_file.unlink()  # a rerun starts a fresh log
    env = make_env(config)
    t0 = time.monotonic()
    make_inference_fn, params, _ = ppo.train(
        environment=env, wrap_env_fn=wrap_for_training, num_timesteps=config.num_timesteps,
        episode_length=env.config.episode_steps, num_envs=config.num_envs, learning_rate=config.learning_rate,
        entropy_cost=config.entropy_cost, discounting=config.discounting, gae_lambda=config.gae_lambda,
        clipping_epsilon=config.clipping_epsilon, unroll_length=config.unroll_length,
        batch_size=config.batch_size, num_minibatches=config.num_minibatches,
        num_updates_per_batch=config.num_updates_per_batch, num_evals=config.num_evals,
        num_eval_envs=config.num_envs, deterministic_eval=True, normalize_observations=True,
        run_evals=config.brax_evals,
        network_factory=ppo_networks(config), seed=config.seed,
        progress_fn=Progress(run_dir, config.num_timesteps, echo=verbose))
    train_s = time.monotonic() - t0
    inference = make_inference_fn(params, deterministic=True)
    report: dict[str, Any] = {"train_wall_s": train_s, "env_steps": config.num_timesteps,
                              "episodes_trained": config.num_timesteps // env.config.episode_steps}
    report.update(evaluate_run(env, lambda obs, k: inference(obs, k)[0], config.eval_episodes,
                               jax.random.PRNGKey(config.seed + 1)))
    if verbose:
        print(json.dumps(report, indent=2), flush=True)
    atomic_write_bytes(run_dir / "params.pkl", pickle.dumps(jax.tree.map(np.asarray, params)))
    atomic_write_bytes(run_dir / "report.json", (json.dumps(json_safe(report), indent=2) + "\n").encode())
    return make_inference_fn, params, report


def evaluate_run(env: V.VelocityMaxEnv, trained: V.Policy, episodes: int, key) -> dict[str, Any]:
    """Metrics of the ``trained`` policy and the random one (and, in safe mode, the optimal
    policy, :func:`velocity_max.optimal_average_velocity`) on the same episodes, in one
    compiled rollout."""
    others = {"trained": trained, "random": V.random_policy(env.action_size)}
    if env.config.mode != "safe":
        return V.evaluate_many(env, others, episodes, key)
    best, info = V.optimal_average_velocity(env, episodes, key, others)
    optimal = {k: info[k] for k in ("violation_rate", "max_position", "max_velocity", "family", "best_factor_share")}
    return {"trained": info["trained"], "random": info["random"], "optimal": {"avg_velocity": best, **optimal}}


def optional_float(text: str) -> float | None:
    """A float, or ``None`` for "none"/"off" (flags of ``float | None`` fields)."""
    if text.strip().lower() in ("none", "off"):
        return None
    try:
        return float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a number or 'none', got {text!r}") from None


def parse_train_args(argv) -> tuple[argparse.Namespace, VelocityTrainConfig]:
    defaults = VelocityTrainConfig()
    parser = argparse.ArgumentParser(prog="python -m mjx_pathtrack.rl.velocity_max_train train",
                                     description="Train PPO on the velocity-maximisation task.")
    parser.add_argument("--out", default=None, help="run directory (default runs/velmax/<mode>_<hz>)")
    parser.add_argument("--quiet", action="store_true")
    for field in dataclasses.fields(VelocityTrainConfig):
        value = getattr(defaults, field.name)
        flag = "--" + field.name.replace("_", "-")
        if isinstance(value, tuple):
            parser.add_argument(flag, type=int, nargs="+", default=list(value))
        elif value is None or "None" in str(field.type):  # optional number, "none" = off
            parser.add_argument(flag, type=optional_float, default=value)
        elif field.name == "mode":
            parser.add_argument(flag, choices=V.MODES, default=value)
        else:
            parser.add_argument(flag, type=type(value), default=value)
    args = parser.parse_args(argv)
    values = {f.name: getattr(args, f.name) for f in dataclasses.fields(VelocityTrainConfig)}
    values["policy_layers"], values["value_layers"] = tuple(values["policy_layers"]), tuple(values["value_layers"])
    config = VelocityTrainConfig(**values)
    config.env_config()  # validates hz, mode, duration
    return args, config


def optimal_main(argv) -> int:
    parser = argparse.ArgumentParser(prog="python -m mjx_pathtrack.rl.velocity_max_train optimal",
                                     description="Average velocity of the optimal and the random policy.")
    parser.add_argument("--hz", type=float, nargs="+", default=list(V.FREQUENCIES))
    parser.add_argument("--episodes", type=int, default=128)
    parser.add_argument("--init-spread", type=float, default=V.VelocityMaxConfig().init_spread)
    parser.add_argument("--search", action="store_true", help="also print the searched family and a perturbation check")
    args = parser.parse_args(argv)
    print("| frequency | random | optimal | optimal violation rate |")
    print("|---|---|---|---|")
    for hz in args.hz:
        env = V.VelocityMaxEnv(V.VelocityMaxConfig(hz=hz, init_spread=args.init_spread))
        best, info = V.optimal_average_velocity(env, args.episodes, jax.random.PRNGKey(0),
                                                {"random": V.random_policy(env.action_size)})
        print(f"| {hz:g} Hz | {info['random']['avg_velocity']:.3f} | {best:.3f} | {info['violation_rate']:.1%} |",
              flush=True)
        if args.search:
            print("   family:", {k: round(v, 4) for k, v in info["family"].items()}, flush=True)
            print("   wins:", {k: round(v, 3) for k, v in info["best_factor_share"].items() if v > 0}, flush=True)
            top = max(info["family"], key=info["family"].get)
            factor = None if top.startswith("factor=None") else float(top.split("=")[1].split("/")[0])
            print(f"   perturbations of {top}:",
                  {k: round(v, 4) for k, v in V.perturbation_check(hz, factor).items()}, flush=True)
    return 0


def main(argv=None) -> int:
    import sys

    argv = sys.argv[1:] if argv is None else list(argv)
    if not argv or argv[0] not in ("train", "optimal"):
        print("usage: python -m mjx_pathtrack.rl.velocity_max_train {train,optimal} [--help]")
        return 2
    if argv[0] == "optimal":
        return optimal_main(argv[1:])
    args, config = parse_train_args(argv[1:])
    out = args.out or f"runs/velmax/{config.mode}_{config.hz:g}"
    train(config, out, verbose=not args.quiet)
    return 0


if __name__ == "__main__":
    import sys

    sys.exit(main())
