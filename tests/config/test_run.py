"""The nested training configuration: flat option names, dotted paths, JSON in both formats."""

import dataclasses
import json

import pytest

from mjx_pathtrack.core.reward import RewardWeights
from mjx_pathtrack.deploy.networks import NetworkConfig
from mjx_pathtrack.envs.tracking import EnvConfig
from mjx_pathtrack.config.run import FLAT_NAMES, PPOConfig, TrainConfig, differences
from mjx_pathtrack.rl.velocity_max_train import VelocityTrainConfig


def test_flat_names_reach_the_nested_fields_and_beta_sets_both_deviation_weights():
    cfg = TrainConfig().replace(alpha=2, beta=0.5, num_envs=64, policy_layers=[32, 16], legs="controlled",
                                ball_reward=0.0, eval_episodes=8)
    assert cfg.env.reward == dataclasses.replace(TrainConfig().env.reward, distance=2.0, max_deviation=0.5,
                                                 mean_deviation=0.5)
    assert isinstance(cfg.env.reward.distance, float)  # an integer becomes the field's float
    assert cfg.network.policy_layers == (32, 16)  # a list becomes the field's tuple
    assert (cfg.ppo.num_envs, cfg.balance.legs, cfg.ball_on_plate.reward, cfg.eval.episodes) == (64, "controlled", 0.0, 8)
    assert cfg.get("alpha") == 2.0 and cfg.get("env.reward.mean_deviation") == 0.5
    # a dotted path reaches a field without a flat name
    assert TrainConfig().replace(**{"env.substeps": 48}).env.substeps == 48
    # every flat name's paths exist, and the flat view covers each of them
    flat = TrainConfig().flat()
    assert list(flat) == list(FLAT_NAMES)
    assert TrainConfig.from_flat(flat) == TrainConfig()
    assert set(differences(TrainConfig(), cfg)) == {"env.reward.distance", "env.reward.max_deviation",
                                                     "env.reward.mean_deviation", "ppo.num_envs",
                                                     "network.policy_layers", "balance.legs", "ball_on_plate.reward",
                                                     "eval.episodes"}


def test_unknown_options_are_named():
    with pytest.raises(ValueError, match="'gamma'"):
        TrainConfig().replace(gamma=0.9)
    with pytest.raises(ValueError, match="env.nonsense"):
        TrainConfig().replace(**{"env.nonsense": 1})
    with pytest.raises(ValueError, match="ppo.bogus"):
        TrainConfig.from_json(json.dumps({**json.loads(TrainConfig().to_json()), "ppo": {"bogus": 1}}))
    with pytest.raises(ValueError, match="flavour"):
        TrainConfig.from_json('{"robot": "iiwa", "flavour": "x"}')


def test_config_json_round_trips_nested_and_the_flat_format_of_old_runs_still_loads():
    cfg = TrainConfig().replace(alpha=2.5, seed=3, mean_clip=1.0, **{"env.start_range": [0.1, 0.5]})
    text = cfg.to_json()
    assert json.loads(text)["env"]["reward"]["distance"] == 2.5
    assert TrainConfig.from_json(text) == cfg
    # a run directory written before the configs were nested: flat keys, old options missing
    old = {"robot": "iiwa", "dataset": "random", "alpha": 2.0, "beta": 0.9, "action_reward": 0.4, "num_envs": 128,
           "policy_layers": [256, 128], "ball_reward": 1.0, "legs": "fixed", "eval_episodes": 64}
    loaded = TrainConfig.from_json(json.dumps(old))
    assert (loaded.env.reward.distance, loaded.ppo.num_envs, loaded.network.policy_layers, loaded.eval.episodes) == (
        2.0, 128, (256, 128), 64)
    # ... with the settings those runs used for the options they did not have
    assert (loaded.env.knots_frame, loaded.env.end_braking, loaded.env.end_stop) == ("absolute", "at_end", "fastest")
    assert (loaded.network.final_noise_std, loaded.network.privileged_critic, loaded.ppo.final_learning_rate) == (
        None, False, None)


def test_blocks_are_the_typed_configs_of_their_concern():
    cfg = TrainConfig()
    assert isinstance(cfg.env, EnvConfig) and isinstance(cfg.env.reward, RewardWeights)
    assert isinstance(cfg.ppo, PPOConfig) and isinstance(cfg.network, NetworkConfig)
    # the environment of a run gets the robot's deviation weights and, for the balance task, its terms
    assert cfg.env.deviation_weights is None and len(cfg.env_config().deviation_weights) == 7
    balance = TrainConfig().replace(task="balance", robot="armar4", executor="mjx", balance_reward=0.5)
    assert balance.env_config().reward.tilt == pytest.approx(1.0) and cfg.env_config().reward.tilt == 0.0
    # Brax's ppo.train takes the PPO block as keyword arguments (it has no learning-rate schedule)
    kwargs = dataclasses.replace(cfg.ppo, final_learning_rate=None).brax_kwargs()
    assert kwargs["num_envs"] == cfg.ppo.num_envs and "final_learning_rate" not in kwargs
    with pytest.raises(ValueError, match="final_learning_rate"):
        cfg.ppo.brax_kwargs()


def test_the_velocity_task_shares_the_blocks_and_loads_its_old_flat_config():
    cfg = VelocityTrainConfig.from_flat({"hz": 60, "num_timesteps": 1000, "mean_clip": None})
    assert (cfg.hz, cfg.ppo.num_timesteps, cfg.network.mean_clip) == (60.0, 1000, None)
    assert VelocityTrainConfig.from_json(cfg.to_json()) == cfg
    old = {"hz": 20.0, "mode": "safe", "num_timesteps": 5000, "policy_layers": [64, 64], "eval_episodes": 32}
    loaded = VelocityTrainConfig.from_json(json.dumps(old))
    assert (loaded.ppo.num_timesteps, loaded.network.policy_layers, loaded.eval.episodes) == (5000, (64, 64), 32)
    with pytest.raises(ValueError, match="discounting"):  # set by horizon_s, not an option here
        VelocityTrainConfig.from_flat({"discounting": 0.5})


def test_a_tighter_training_tube_ends_only_the_training_episodes_earlier():
    """``--train-terminate-deviation``: the training split's environments end episodes at that
    deviation, the evaluation split (and so the training's evaluations and every report) at the
    bar ``--terminate-deviation``; a tube wider than the bar, or not a number > 0, is refused."""
    from mjx_pathtrack.config.run import ConfigError, validate_config
    from mjx_pathtrack.envs import registry

    config = TrainConfig().replace(train_terminate_deviation=0.15)
    validate_config(config)
    assert registry.make(config, "train").config.terminate_deviation == 0.15
    assert registry.make(config, "test").config.terminate_deviation == 0.25
    assert registry.make(TrainConfig(), "train").config.terminate_deviation == 0.25   # unset: the bar
    for bad, message in ((0.3, "0.3 is above --terminate-deviation 0.25"), (0.0, "must be a finite number > 0"),
                         (float("nan"), "must be a finite number > 0")):
        with pytest.raises(ConfigError, match=f"--train-terminate-deviation: {message}"):
            validate_config(TrainConfig().replace(train_terminate_deviation=bad))
