"""PPO training and evaluation for the velocity-maximisation task (paper 001 Tables I and II).

    python -m mjx_pathtrack.rl.velocity_max_train train --hz 10 --mode safe --num-timesteps 300000 --out runs/velmax/safe_10
    python -m mjx_pathtrack.rl.velocity_max_train optimal                 # optimal vs random, all frequencies
    python -m mjx_pathtrack.rl.velocity_max_train optimal --search        # + the optimality check

Reuses the project's Brax PPO machinery (:func:`mjx_pathtrack.deploy.networks.networks`,
:class:`~mjx_pathtrack.rl.training.Progress`, :func:`~mjx_pathtrack.envs.wrappers.wrap_for_training`).
A run directory gets ``config.json``, ``progress.csv``, ``tensorboard/``, ``params.msgpack`` and
``report.json`` (trained, random and optimal policy evaluated on the same episodes).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import time
from pathlib import Path
from typing import Any

from mjx_pathtrack.fileio import atomic_write_bytes  # first: the package sets the CPU XLA flags before JAX starts
from mjx_pathtrack.envs.tasks import velocity_max as V
from mjx_pathtrack.config.run import EvalConfig, NetworkConfig, PPOConfig
from mjx_pathtrack.config.options import Options, add_flags, from_flags
from mjx_pathtrack.config.stored import PARAMS_FILE, params_bytes

import jax


@dataclasses.dataclass(frozen=True)
class VelocityTrainConfig(Options):
    """A training run (saved as ``config.json``): the task (``hz``, ``mode``, ``duration``,
    ``init_spread``), ``horizon_s`` [s], which sets the discount per step, ``1 - dt / horizon_s``
    (so that every frequency looks the same time ahead; ``ppo.discounting`` is not used), and the
    shared PPO / network / evaluation blocks of :mod:`mjx_pathtrack.config.run`, sized for a CPU
    budget (the task is per-joint and nearly myopic). The network's mean is bounded
    (``mean_clip`` 1): without it the 120/240 Hz policies drift to means far outside [-1, 1] and
    stop exploring (docs/results.md "Paper 001 experiments"); ``--mean-clip none`` turns it off.
    ``brax_evals``: run Brax's evaluator ``num_evals`` times (the eval return in
    ``progress.csv``); off by default because its compilation costs as much as a short run on
    a shared CPU -- the final evaluation (``report.json``) is always done."""

    hz: float = 20.0
    mode: str = "safe"
    duration: float = 5.0
    init_spread: float = 0.5
    horizon_s: float = 1.0
    brax_evals: bool = False
    seed: int = 0
    ppo: PPOConfig = PPOConfig(num_timesteps=300_000, num_envs=64, learning_rate=1e-3, final_learning_rate=None,
                               unroll_length=16, batch_size=64, num_minibatches=4, num_updates_per_batch=4)
    network: NetworkConfig = NetworkConfig(policy_layers=(64, 64), value_layers=(64, 64), final_noise_std=None,
                                           mean_clip=1.0, privileged_critic=False)
    eval: EvalConfig = EvalConfig(num_evals=4, episodes=128)

    def env_config(self) -> V.VelocityMaxConfig:
        return V.VelocityMaxConfig(hz=self.hz, mode=self.mode, duration=self.duration, init_spread=self.init_spread)

    @property
    def discounting(self) -> float:
        return max(0.0, 1.0 - 1.0 / (self.hz * self.horizon_s))


#: flat option names (command-line flags, keys of run directories' flat config.json files)
VelocityTrainConfig.FLAT_NAMES = {
    **{name: (name,) for name in ("hz", "mode", "duration", "init_spread", "horizon_s", "brax_evals", "seed")},
    **{f.name: (f"ppo.{f.name}",) for f in dataclasses.fields(PPOConfig)
       if f.name not in ("discounting", "final_learning_rate")},
    **{f.name: (f"network.{f.name}",) for f in dataclasses.fields(NetworkConfig)
       if f.name not in ("final_noise_std", "privileged_critic")},
    "num_evals": ("eval.num_evals",),
    "eval_episodes": ("eval.episodes",),
}


def make_env(config: VelocityTrainConfig) -> V.VelocityMaxEnv:
    return V.VelocityMaxEnv(config.env_config())


def train(config: VelocityTrainConfig, run_dir: str | Path, verbose: bool = True):
    """Train PPO; returns ``(make_inference_fn, params, report)``. ``report`` holds the
    evaluation (:func:`velocity_max.evaluate`) of the trained (deterministic), random and
    optimal policies on ``eval_episodes`` episodes and the wall time."""
    from brax.training.agents.ppo import train as ppo

    from mjx_pathtrack.deploy.networks import policy_network_factory
    from mjx_pathtrack.fileio import json_safe
    from mjx_pathtrack.rl.training import Progress
    from mjx_pathtrack.envs.wrappers import wrap_for_training

    run_dir = Path(run_dir)
    run_dir.mkdir(parents=True, exist_ok=True)
    atomic_write_bytes(run_dir / "config.json", config.to_json().encode())
    progress_file = run_dir / "progress.csv"
    if progress_file.exists():
        progress_file.unlink()  # a rerun starts a fresh log
    env = make_env(config)
    t0 = time.monotonic()
    make_inference_fn, params, _ = ppo.train(
        environment=env, wrap_env_fn=wrap_for_training, episode_length=env.config.episode_steps,
        **dataclasses.replace(config.ppo, discounting=config.discounting).brax_kwargs(),
        num_evals=config.eval.num_evals, num_eval_envs=config.ppo.num_envs, deterministic_eval=True,
        normalize_observations=True, run_evals=config.brax_evals,
        network_factory=policy_network_factory(config), seed=config.seed,
        progress_fn=Progress(run_dir, config.ppo.num_timesteps, echo=verbose))
    train_s = time.monotonic() - t0
    inference = make_inference_fn(params, deterministic=True)
    report: dict[str, Any] = {"train_wall_s": train_s, "env_steps": config.ppo.num_timesteps,
                              "episodes_trained": config.ppo.num_timesteps // env.config.episode_steps}
    report.update(evaluate_run(env, lambda obs, k: inference(obs, k)[0], config.eval.episodes,
                               jax.random.PRNGKey(config.seed + 1)))
    if verbose:
        print(json.dumps(report, indent=2), flush=True)
    atomic_write_bytes(run_dir / PARAMS_FILE, params_bytes(params))
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
    parser = argparse.ArgumentParser(prog="python -m mjx_pathtrack.rl.velocity_max_train train",
                                     description="Train PPO on the velocity-maximisation task.")
    parser.add_argument("--out", default=None, help="run directory (default runs/velmax/<mode>_<hz>)")
    parser.add_argument("--quiet", action="store_true")
    add_flags(parser, VelocityTrainConfig, {"mode": V.MODES})
    args = parser.parse_args(argv)
    config = from_flags(args, VelocityTrainConfig)
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
