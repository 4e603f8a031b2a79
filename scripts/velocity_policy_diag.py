"""What a trained velocity-maximisation policy does, joint by joint, in one deterministic episode.

    python scripts/velocity_policy_diag.py RUN_DIR [--seed 3]

``RUN_DIR`` is a run of ``python -m mjx_pathtrack.rl.velocity_max_train train`` (config.json +
params.msgpack). The optimal policy takes a = sign(v) = ±1 and reverses at the position limits, so
the script prints per joint: mean |a| (the action before the environment clips it to [-1, 1]),
the share of steps with |a| > 0.95, the share of moving steps (|v| > 0.05 v_max) in which
sign(a) = sign(v), the share of steps at rest (|v| <= 0.05 v_max) and the mean |v| / v_max.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from mjx_pathtrack.rl import velocity_max_train as T  # first: the package sets the XLA flags

import jax
import numpy as np


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("run")
    parser.add_argument("--seed", type=int, default=3, help="start state of the episode")
    args = parser.parse_args()
    from brax.training.agents.ppo import networks as ppo_nets

    from mjx_pathtrack.config.stored import read_params
    from mjx_pathtrack.deploy.networks import policy_networks

    run = Path(args.run)
    config = T.VelocityTrainConfig.from_json((run / "config.json").read_text())
    env = T.make_env(config)
    params, _ = read_params(run)
    nets = policy_networks(config, env.observation_size, env.action_size)
    inference = ppo_nets.make_inference_fn(nets)(params, deterministic=True)
    act = jax.jit(lambda obs: inference(obs, jax.random.PRNGKey(0))[0])
    step = jax.jit(env.step)
    state = env.reset(jax.random.PRNGKey(args.seed))
    actions, speeds = [], []
    for _ in range(env.config.episode_steps):
        a = act(state.obs)
        actions.append(np.asarray(a))
        speeds.append(np.asarray(state.pipeline_state.v / env.limits.vel))
        state = step(state, a)
    a, v = np.array(actions), np.array(speeds)
    moving = np.abs(v) > 0.05
    agree = [float(np.mean((np.sign(a[:, j]) == np.sign(v[:, j]))[moving[:, j]])) if moving[:, j].any()
             else float("nan") for j in range(a.shape[1])]
    print(f"{run}: {config.hz:g} Hz, {config.num_timesteps:,} env steps, episode seed {args.seed}")
    for name, values in (("mean |a|", np.abs(a).mean(0)), ("share |a| > 0.95", (np.abs(a) > 0.95).mean(0)),
                         ("sign(a) = sign(v), moving", agree), ("share at rest", (~moving).mean(0)),
                         ("mean |v| / v_max", np.abs(v).mean(0))):
        print(f"{name:>26}: " + " ".join(f"{x:5.2f}" for x in values))


if __name__ == "__main__":
    main()
