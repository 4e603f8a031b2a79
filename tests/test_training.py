"""train.py / training.py on tiny runs: outputs, determinism, resume, two host devices."""

import csv
import json
import os
import pickle
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

import mjx_pathtrack  # noqa: F401
import jax

from mjx_pathtrack.export import load_policy
from mjx_pathtrack.training import TrainConfig, json_safe, latest_checkpoint, train

REPO = Path(__file__).resolve().parents[1]
TINY = dict(num_envs=8, num_timesteps=640, unroll_length=5, batch_size=8, num_minibatches=2,
            num_updates_per_batch=1, num_evals=2, eval_episodes=4, policy_layers=(16,), value_layers=(16,),
            duration=4.0)


def tiny_args(out):
    args = ["--out", str(out)]
    for key, value in TINY.items():
        flag = "--" + key.replace("_", "-")
        args += [flag, *map(str, value)] if isinstance(value, tuple) else [flag, str(value)]
    return args


@pytest.fixture(scope="module")
def tiny_run(tmp_path_factory):
    out = tmp_path_factory.mktemp("run")
    config = TrainConfig(**TINY)
    _, params, report = train(config, out, verbose=False)
    return out, config, params, report


def test_run_directory_has_config_progress_checkpoint_and_report(tiny_run):
    out, config, params, report = tiny_run
    assert TrainConfig.from_json((out / "config.json").read_text()) == config
    assert set(report) == {"before", "after"}
    for summary in report.values():
        assert set(summary) >= {"return", "end_reached", "mean_deviation", "stop_time_s"}
        assert np.isfinite(summary["return"])
    assert json.loads((out / "report.json").read_text()) == json_safe(report)
    rows = list(csv.DictReader(open(out / "progress.csv")))
    assert list(rows[0])[:4] == ["step", "wall_s", "env_steps_per_s", "eta_s"] and len(rows) >= 2  # one per evaluation
    assert float(rows[0]["step"]) == 0 and float(rows[-1]["step"]) >= config.num_timesteps
    # the rows show this package's evaluation: the first is the report's "before", the last its "after"
    for row, summary in ((rows[0], report["before"]), (rows[-1], report["after"])):
        assert float(row["eval/end_reached"]) == pytest.approx(summary["end_reached"])
        assert float(row["eval/return"]) == pytest.approx(summary["return"])
    assert "training/sps" in rows[-1] and float(rows[-1]["env_steps_per_s"]) > 0
    assert any(p.name.startswith("events.out.tfevents") for p in (out / "tensorboard").iterdir())
    latest = latest_checkpoint(out / "checkpoints")
    assert latest is not None and latest[1] > 0
    policy = load_policy(out / "export")
    assert policy.manifest["robot"] == "iiwa" and policy(np.zeros(94, np.float32)).shape == (7,)
    saved = pickle.loads((out / "params.pkl").read_bytes())
    np.testing.assert_array_equal(jax.tree.leaves(saved)[0], np.asarray(jax.tree.leaves(params)[0]))


def test_same_seed_same_parameters(tiny_run, tmp_path):
    _, config, params, _ = tiny_run
    _, again, _ = train(config, tmp_path, verbose=False)
    for a, b in zip(jax.tree.leaves(params), jax.tree.leaves(again)):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))


def test_resume_continues_from_the_last_checkpoint(tiny_run, tmp_path):
    out, config, _, _ = tiny_run
    # a copy of the finished run with a larger budget resumes from its last checkpoint
    run = tmp_path / "run"
    subprocess.run(["cp", "-r", str(out), str(run)], check=True)
    _, done = latest_checkpoint(run / "checkpoints")
    bigger = TrainConfig(**{**TINY, "num_timesteps": 2 * done})
    (run / "config.json").write_text(json.dumps({**json.loads((run / "config.json").read_text()),
                                                 "num_timesteps": 2 * done}))
    train(bigger, run, resume=True, verbose=False)
    _, total = latest_checkpoint(run / "checkpoints")
    assert total > done
    with pytest.raises(ValueError, match="differs"):
        train(TrainConfig(**{**TINY, "seed": 5}), run, resume=True, verbose=False)


def test_train_cli_on_two_forced_host_devices(tmp_path):
    env = dict(os.environ, XLA_FLAGS="--xla_force_host_platform_device_count=2")
    cache = tmp_path / "jax_cache"
    result = subprocess.run([sys.executable, "train.py", *tiny_args(tmp_path / "run"), "--compilation-cache", str(cache)],
                            cwd=REPO, env=env, capture_output=True, text=True, timeout=900)
    assert result.returncode == 0, result.stderr[-3000:]
    assert "CpuDevice(id=1)" in result.stdout  # both devices visible to Brax's pmap
    assert "evaluation after training" in result.stdout
    assert (tmp_path / "run" / "params.pkl").is_file()
    assert any(cache.iterdir())  # compiled programs went to the persistent cache


def test_compilation_cache_is_opt_in_and_a_bad_directory_is_a_clear_error(tmp_path):
    import train as cli

    args, _ = cli.parse_args([])
    assert args.compilation_cache is None
    blocker = tmp_path / "a_file"
    blocker.write_text("")
    with pytest.raises(SystemExit, match="--compilation-cache .*cannot create"):
        cli.use_compilation_cache(str(blocker / "cache"))


def test_presets_set_the_papers_settings_as_flag_defaults():
    sys.path.insert(0, str(REPO))
    import train as cli

    args, cfg = cli.parse_args(["--robot", "armar6"])
    assert (cfg.robot, cfg.executor, cfg.alpha, cfg.duration, cfg.action_reward) == ("armar6", "kinematic", 1.0, 20.0, 0.0)
    assert args.out == "runs/armar6_random"
    args, cfg = cli.parse_args(["--task", "balance", "--legs", "controlled", "--alpha", "3"])
    assert (cfg.task, cfg.legs, cfg.robot, cfg.executor, cfg.balance_reward) == ("balance", "controlled", "armar4", "mjx", 1.0)
    assert cfg.alpha == 3.0 and cfg.duration == 20.0 and args.out == "runs/balance_controlled"  # explicit flags win
    assert cli.parse_args([])[1] == TrainConfig()  # no preset for the iiwa: the defaults
    with pytest.raises(SystemExit):
        cli.parse_args(["--task", "juggling"])
    assert cli.parse_args(["--knots-frame", "absolute"])[1].env_config().knots_frame == "absolute"
    assert TrainConfig().knots_frame == "relative"
    # a run directory from before the option existed observed absolute knots
    assert TrainConfig.from_json('{"robot": "iiwa"}').knots_frame == "absolute"
    with pytest.raises(SystemExit):
        cli.parse_args(["--knots-frame", "polar"])


def test_mean_clip_bounds_the_policy_mean():
    from brax.training.acme import running_statistics, specs
    from brax.training.agents.ppo import networks as ppo_nets

    from mjx_pathtrack.training import ppo_networks

    obs = jax.random.uniform(jax.random.PRNGKey(1), (64, 10), minval=-1, maxval=1)
    norm = running_statistics.init_state(specs.Array((10,), np.dtype("float32")))
    means = {}
    for clip in (None, 1.0):  # a mean head initialised far too large: only the bound keeps it inside (-1, 1)
        config = TrainConfig(policy_layers=(16,), value_layers=(8,), mean_init_scale=30.0, mean_clip=clip)
        nets = ppo_networks(config)(10, 3, preprocess_observations_fn=running_statistics.normalize)
        params = (norm, nets.policy_network.init(jax.random.PRNGKey(0)))
        means[clip] = np.asarray(ppo_nets.make_inference_fn(nets)(params, deterministic=True)(obs, None)[0])
    assert np.abs(means[None]).max() > 2.0
    assert np.abs(means[1.0]).max() < 1.0
    np.testing.assert_allclose(means[1.0], means[None] / (1.0 + np.abs(means[None])), rtol=1e-5, atol=1e-6)
