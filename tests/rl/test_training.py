"""train.py / training.py on tiny runs: outputs, determinism, resume, two host devices."""

import csv
import dataclasses
import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

import mjx_pathtrack  # noqa: F401
import jax
import jax.numpy as jnp

from mjx_pathtrack.deploy.export import load_policy
from mjx_pathtrack.config import run_dir
from mjx_pathtrack.config.run_dir import latest_checkpoint
from mjx_pathtrack.config.stored import PARAMS_FILE, params_bytes, read_params
from mjx_pathtrack.config.run import TrainConfig
from mjx_pathtrack.fileio import json_safe
from mjx_pathtrack.rl.training import make_env, train

REPO = Path(__file__).resolve().parents[2]
TINY = dict(num_envs=8, num_timesteps=640, unroll_length=5, batch_size=8, num_minibatches=2,
            num_updates_per_batch=1, num_evals=2, eval_episodes=4, policy_layers=(16,), value_layers=(16,),
            duration=4.0)


def tiny_args(out):
    """train.py flags of ``TrainConfig().replace(**TINY)`` (the CLI's iiwa default dataset is
    mixed; TrainConfig's is random)."""
    args = ["--out", str(out), "--dataset", TrainConfig().dataset]
    for key, value in TINY.items():
        flag = "--" + key.replace("_", "-")
        args += [flag, *map(str, value)] if isinstance(value, tuple) else [flag, str(value)]
    return args


@pytest.fixture(scope="module")
def tiny_run(tmp_path_factory):
    out = tmp_path_factory.mktemp("run")
    config = TrainConfig().replace(**TINY)
    _, params, report = train(config, out, verbose=False)
    return out, config, params, report


def test_run_directory_has_config_progress_checkpoint_and_report(tiny_run):
    out, config, params, report = tiny_run
    assert TrainConfig.from_json((out / "config.json").read_text()) == config
    assert set(report) == {"before", "after", "before_sampled", "after_sampled"}
    for summary in report.values():
        assert set(summary) >= {"return", "end_reached", "mean_deviation", "stop_time_s"}
        assert np.isfinite(summary["return"])
    assert json.loads((out / "report.json").read_text()) == json_safe(report)
    rows = list(csv.DictReader(open(out / "progress.csv")))
    assert list(rows[0])[:4] == ["step", "wall_s", "env_steps_per_s", "eta_s"] and len(rows) >= 2  # one per evaluation
    assert float(rows[0]["step"]) == 0 and float(rows[-1]["step"]) >= config.ppo.num_timesteps
    # the rows show this package's evaluation, deterministic and sampled: the first is the
    # report's "before", the last its "after"
    for row, when in ((rows[0], "before"), (rows[-1], "after")):
        for prefix, key in (("eval", when), ("eval_sampled", f"{when}_sampled")):
            assert float(row[f"{prefix}/end_reached"]) == pytest.approx(report[key]["end_reached"])
            assert float(row[f"{prefix}/return"]) == pytest.approx(report[key]["return"])
    assert report["after"]["return"] != report["after_sampled"]["return"]  # two different policies
    assert "training/total_loss" in rows[-1] and float(rows[-1]["env_steps_per_s"]) > 0
    assert any(p.name.startswith("events.out.tfevents") for p in (out / "tensorboard").iterdir())
    latest = latest_checkpoint(out / "checkpoints")
    assert latest is not None and latest[1] > 0
    policy = load_policy(out / "export")
    assert policy.manifest["robot"] == "iiwa" and policy(np.zeros(94, np.float32)).shape == (7,)
    saved = read_params(out)[0]
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
    bigger = TrainConfig.from_flat({**TINY, "num_timesteps": 2 * done})
    (run / "config.json").write_text(TrainConfig.from_json((run / "config.json").read_text())
                                     .replace(num_timesteps=2 * done).to_json())
    train(bigger, run, resume=True, verbose=False)
    _, total = latest_checkpoint(run / "checkpoints")
    assert total > done
    with pytest.raises(ValueError, match="differs .*seed"):
        train(TrainConfig.from_flat({**TINY, "seed": 5}), run, resume=True, verbose=False)


def test_init_from_starts_where_the_source_run_ended(tiny_run, tmp_path):
    out, config, params, report = tiny_run
    warm = config.replace(init_from=str(out))  # same seed: the same evaluation episodes
    _, tuned, warm_report = train(warm, tmp_path / "warm", verbose=False)
    # its evaluation before training is the source's final one (deterministic: the policy's mean,
    # normalised observations; the sampled one differs: the std schedule starts afresh) ...
    assert warm_report["before"] == pytest.approx(report["after"], nan_ok=True)
    # ... and it trains on from there
    assert any(not np.array_equal(np.asarray(a), np.asarray(b)) for a, b in zip(jax.tree.leaves(params),
                                                                                   jax.tree.leaves(tuned)))
    assert TrainConfig.from_json((tmp_path / "warm" / "config.json").read_text()).init_from == str(out)


def _first_kernel(net):
    return net["params"]["MLP_0"]["hidden_0"]["kernel"] if "MLP_0" in net["params"] else net["params"]["hidden_0"]["kernel"]


def _trimmed_source(out, where, cut_inputs, manifest, cut_action=None):
    """A run directory ``where`` holding the tiny run ``out``'s parameters without the observation
    entries ``cut_inputs`` (and the action ``cut_action``), with the export ``manifest``."""
    norm, policy, value = jax.tree.map(np.asarray, read_params(out)[0])

    def trim(x, axis=0):
        return np.delete(np.asarray(x), cut_inputs, axis=axis)

    norm = norm.replace(mean=trim(norm.mean), std=trim(norm.std), summed_variance=trim(norm.summed_variance))
    for net in (policy, value):
        first = net["params"]["MLP_0"] if "MLP_0" in net["params"] else net["params"]
        first["hidden_0"]["kernel"] = trim(first["hidden_0"]["kernel"])
    if cut_action is not None:
        head = policy["params"]["Dense_0"]
        head["kernel"], head["bias"] = np.delete(head["kernel"], cut_action, 1), np.delete(head["bias"], cut_action)
        std = policy["params"]["std_logparam"]
        std["log_value"] = np.delete(std["log_value"], cut_action)
    (where / "export").mkdir(parents=True)
    (where / PARAMS_FILE).write_bytes(params_bytes((norm, policy, value)))
    (where / "export" / "manifest.json").write_text(json.dumps(manifest))
    return where


def test_init_from_a_run_with_fewer_observations_adds_them_with_zero_weights(tiny_run, tmp_path):
    """A source that lacks some of this run's observation blocks (here: the tiny run without its
    last block, the 8 knot distances; in use: a plain tracking run before the balance task's pelvis
    blocks): its parameters come in unchanged, the added inputs with zero weights in both
    networks' first layers and a unit normaliser. A run that lacks one of the source's blocks is
    refused."""
    from mjx_pathtrack.rl import training
    from mjx_pathtrack.rl import warm_start as warm
    from mjx_pathtrack.config.run_dir import RunDirError

    out, config, _, _ = tiny_run
    manifest = json.loads((out / "export" / "manifest.json").read_text())
    layout = manifest["observation_layout"]
    block = layout[-1]
    cut = np.arange(block["start"], block["start"] + block["size"])  # 86..93; the value net's 3 extra after
    source = _trimmed_source(out, tmp_path / "fewer", cut, {**manifest, "observation_layout": layout[:-1]})
    norm, policy, value = read_params(out)[0]
    env = make_env(config, "train")
    learner = training._program(config, env).init(config.seed)
    target = warm.PolicyLayout.of_env(env, manifest["joint_names"])
    warm_learner, new = warm.warm_start(learner, source, 1, target)
    assert len(new) == 0  # the same joints
    got_norm = warm_learner.normalizer_params
    count = float(int(norm.count))
    keep = np.setdiff1d(np.arange(len(np.asarray(norm.mean))), cut)
    np.testing.assert_array_equal(np.asarray(got_norm.mean)[keep], np.asarray(norm.mean)[keep])
    np.testing.assert_array_equal(np.asarray(got_norm.mean)[cut], 0.0)
    np.testing.assert_array_equal(np.asarray(got_norm.std)[cut], 1.0)
    np.testing.assert_allclose(np.asarray(got_norm.summed_variance)[cut], count, rtol=1e-6)
    for got, was in ((warm_learner.params.policy, policy), (warm_learner.params.value, value)):
        k_got, k_was = np.asarray(_first_kernel(got)), np.asarray(_first_kernel(was))
        np.testing.assert_array_equal(k_got[cut], 0.0)
        np.testing.assert_array_equal(k_got[np.setdiff1d(np.arange(len(k_got)), cut)],
                                      k_was[np.setdiff1d(np.arange(len(k_was)), cut)])
    with pytest.raises(RunDirError, match="observation normaliser parameter .mean has shape"):  # without the layouts
        warm.warm_start(learner, source, 1, None)
    renamed = dataclasses.replace(target, observation=tuple(dict(b, name="x" if i == 0 else b["name"])
                                                            for i, b in enumerate(target.observation)))
    with pytest.raises(RunDirError, match=r"source run observes \['position'\], this run does not"):
        warm.warm_start(learner, source, 1, renamed)


@pytest.mark.slow
def test_init_from_a_run_with_fewer_joints_fits_the_new_one_to_hold_still(tiny_run, tmp_path):
    """A source that drove one joint fewer (as the fixed-legs ARMAR-4 policy for controlled legs):
    the source's joints act as before whatever the new joint's inputs, the new joint's mean action
    starts at 0 and the fit then moves it towards braking and holding still (its hold action)
    while the source's joints keep their actions."""
    from mjx_pathtrack.deploy.export import observation_layout
    from mjx_pathtrack.rl import training
    from mjx_pathtrack.rl import warm_start as warm

    out, config, _, _ = tiny_run
    manifest = json.loads((out / "export" / "manifest.json").read_text())
    names, n, n_next = manifest["joint_names"], len(manifest["joint_names"]), manifest["n_next"]
    assert manifest["path_joints"] == list(range(n))
    drop = n - 1
    blocks = {b["name"]: b for b in manifest["observation_layout"]}
    cut = [blocks[k]["start"] + drop for k in ("position", "velocity", "acceleration")]
    cut += [blocks["knots"]["start"] + k * n + drop for k in range(n_next + 1)]
    small = {**manifest, "joint_names": names[:drop], "path_joints": list(range(drop)),
             "observation_layout": observation_layout(drop, drop, n_next)}
    source = _trimmed_source(out, tmp_path / "fewer_joints", cut, small, cut_action=drop)
    env = make_env(config, "train")
    program = training._program(config, env)
    learner = program.init(config.seed)
    warm_learner, new = warm.warm_start(learner, source, 1, warm.PolicyLayout.of_env(env, names))
    assert new.tolist() == [drop]
    full = read_params(out)[0]
    np.testing.assert_array_equal(np.asarray(warm_learner.params.policy["params"]["std_logparam"]["log_value"])[drop],
                                  np.asarray(learner.params.policy["params"]["std_logparam"]["log_value"])[drop])

    def act(learner_or_params, obs):
        params = (learner_or_params.normalizer_params, learner_or_params.params.policy) \
            if hasattr(learner_or_params, "params") else learner_or_params
        return np.asarray(program.core.make_policy(params, deterministic=True)(obs, None)[0])

    obs = jax.random.uniform(jax.random.PRNGKey(3), (64, env.observation_size), minval=-1.0, maxval=1.0)
    moved = obs.at[:, np.asarray(cut)].set(-obs[:, np.asarray(cut)])
    warm_act = act(warm_learner, obs)
    np.testing.assert_array_equal(warm_act[:, drop], 0.0)  # the new joint: mean 0, the middle of its range
    np.testing.assert_array_equal(act(warm_learner, moved)[:, :drop], warm_act[:, :drop])  # blind to its inputs
    # the source's joints act as the source did where the inputs it knew are the same (the
    # tiny run's own parameters see the dropped joint's inputs, so compare with those zeroed)
    src = jax.tree.map(np.asarray, full)
    src_policy = src[1]
    _first_kernel(src_policy)[np.asarray(cut)] = 0.0
    np.testing.assert_allclose(warm_act[:, :drop], act((warm_learner.normalizer_params, src_policy), obs)[:, :drop],
                               atol=1e-6)

    fitted, report = warm.fit_new_joints(program.core.make_policy, warm_learner, env, new, 1, jax.random.PRNGKey(4),
                                         n_envs=16, n_steps=10, iterations=300)
    assert report["states"] > 100
    assert report["rms_new_after"] < 0.2 * report["rms_new_before"], report
    assert report["rms_old_before"] < 1e-6 and report["rms_old_after"] < 0.05, report


def test_init_from_refuses_other_networks_and_missing_runs(tiny_run, tmp_path):
    from mjx_pathtrack.config.options import ConfigError
    from mjx_pathtrack.config.run_dir import RunDirError

    out, config, _, _ = tiny_run
    with pytest.raises(RunDirError, match="policy.*shape .*this run's"):
        train(config.replace(init_from=str(out), policy_layers=(8,)), tmp_path / "other", verbose=False)
    assert not (tmp_path / "other").exists()  # nothing left behind
    with pytest.raises(ConfigError, match="--init-from: .*no params.msgpack"):
        train(config.replace(init_from=str(tmp_path / "nowhere")), tmp_path / "missing", verbose=False)
    assert not (tmp_path / "missing").exists()


@pytest.mark.slow
def test_train_cli_on_two_forced_host_devices(tmp_path):
    env = dict(os.environ, XLA_FLAGS="--xla_force_host_platform_device_count=2")
    cache = tmp_path / "jax_cache"
    result = subprocess.run([sys.executable, "train.py", *tiny_args(tmp_path / "run"), "--compilation-cache", str(cache)],
                            cwd=REPO, env=env, capture_output=True, text=True, timeout=900)
    assert result.returncode == 0, result.stderr[-3000:]
    assert "CpuDevice(id=1)" in result.stdout  # both devices visible to Brax's pmap
    assert "evaluation after training" in result.stdout
    assert (tmp_path / "run" / "params.msgpack").is_file()
    assert any(cache.iterdir())  # compiled programs went to the persistent cache
    # the last lines list what the run holds and how to use it
    run = tmp_path / "run"
    assert f"run directory {run}: config.json, progress.csv, tensorboard/, checkpoints/, params.msgpack, report.json, " \
           f"export/" in result.stdout
    assert "export/: manifest.json, policy.jaxexport, policy.onnx" in result.stdout
    assert f"python evaluate.py {run}/export" in result.stdout.splitlines()[-5]
    assert f"python evaluate.py {run}/export --full-paths --episodes 1 --video" in result.stdout.splitlines()[-2]


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
    assert (cfg.robot, cfg.executor, cfg.env.reward.distance, cfg.env.duration, cfg.env.reward.action) == ("armar6", "kinematic", 1.0, 20.0, 0.0)
    assert (cfg.num_train_paths, cfg.ppo.num_timesteps) == (60, 24_000_000)  # this package's ARMAR-6 budget
    assert args.out == "runs/armar6_random"
    args, cfg = cli.parse_args(["--task", "balance", "--legs", "controlled", "--alpha", "3"])
    assert (cfg.task, cfg.balance.legs, cfg.robot, cfg.executor, cfg.balance.reward) == ("balance", "controlled", "armar4", "mjx", 1.0)
    assert cfg.env.reward.distance == 3.0 and cfg.env.duration == 20.0 and args.out == "runs/balance_controlled"  # explicit flags win
    assert cfg.env.substeps == 24  # controlled legs: the papers' 240 Hz physics; fixed legs 80 Hz unless given
    assert cli.parse_args(["--task", "balance"])[1].env.substeps == 8
    assert cli.parse_args(["--task", "balance", "--substeps", "24"])[1].env.substeps == 24
    assert cli.parse_args([])[1] == TrainConfig().replace(dataset="mixed")  # the iiwa's preset: its mixed paths
    with pytest.raises(SystemExit):
        cli.parse_args(["--task", "juggling"])
    assert cli.parse_args(["--knots-frame", "absolute"])[1].env_config().knots_frame == "absolute"
    assert TrainConfig().env.knots_frame == "relative"
    # a run directory from before the option existed observed absolute knots
    assert TrainConfig.from_json('{"robot": "iiwa"}').env.knots_frame == "absolute"
    assert TrainConfig.from_json('{"robot": "iiwa"}').network.final_noise_std is None  # ... and learned their std
    with pytest.raises(SystemExit):
        cli.parse_args(["--knots-frame", "polar"])
    # a yes/no option is a flag pair, not a value ("--privileged-critic False" would be true)
    assert cli.parse_args(["--privileged-critic"])[1].network.privileged_critic is True
    assert cli.parse_args(["--privileged-critic", "--no-privileged-critic"])[1].network.privileged_critic is False
    assert TrainConfig.from_json('{"robot": "iiwa"}').network.privileged_critic is False
    # new runs stop at the end knot; runs from before the option stopped every joint as fast as it could
    assert (TrainConfig().env.end_stop, TrainConfig.from_json('{"robot": "iiwa"}').env.end_stop) == ("end_knot", "fastest")
    assert cli.parse_args(["--end-stop", "fastest"])[1].env_config().end_stop == "fastest"
    with pytest.raises(SystemExit):
        cli.parse_args(["--end-stop", "never"])
    with pytest.raises(SystemExit):
        cli.parse_args(["--privileged-critic", "False"])


def test_preset_paper_is_the_recipe_at_a_larger_budget_and_explicit_flags_win():
    sys.path.insert(0, str(REPO))
    import train as cli
    from mjx_pathtrack.config.presets import RECIPES, recipe

    # the iiwa trains on the mixed paths by default (docs/paths.md §5)
    args, cfg = cli.parse_args([])
    assert (args.out, cfg.dataset) == ("runs/iiwa_mixed", "mixed") and cfg == TrainConfig().replace(dataset="mixed")
    args, cfg = cli.parse_args(["--preset", "paper"])
    assert args.out == "runs/iiwa_mixed_paper"
    assert cfg == TrainConfig().replace(dataset="mixed", **recipe("paper", "iiwa", "mixed"))
    assert cfg.ppo.num_timesteps > TrainConfig().ppo.num_timesteps
    # the default recipe, longer, with the papers' alpha: the privileged critic, the falling
    # learning rate and predictive braking are the defaults of both
    default = TrainConfig().replace(dataset="mixed")
    assert cfg.replace(num_timesteps=default.ppo.num_timesteps, num_evals=default.eval.num_evals,
                       alpha=default.env.reward.distance) == default
    assert (cfg.env.reward.distance, cfg.num_train_paths) == (2.0, 0)
    # on the random paths: also their 1000 regenerated train paths
    args, cfg = cli.parse_args(["--preset", "paper", "--dataset", "random"])
    assert args.out == "runs/iiwa_random_paper" and (cfg.env.reward.distance, cfg.num_train_paths) == (2.0, 1000)
    assert (cfg.network.privileged_critic, cfg.ppo.final_learning_rate, cfg.env.end_braking, cfg.env.end_stop) == (
        True, 3e-5, "predictive", "end_knot")
    args, cfg = cli.parse_args(["--preset", "paper", "--robot", "armar6", "--num-timesteps", "1000"])
    # the iiwa's alpha and train paths are not applied to another robot
    assert (cfg.robot, cfg.env.reward.distance, cfg.ppo.num_timesteps, cfg.eval.num_evals) == ("armar6", 1.0, 1000, RECIPES["paper"]["num_evals"])
    assert cfg.num_train_paths == 60
    # nor to another task or dataset of the iiwa
    _, cfg = cli.parse_args(["--preset", "paper", "--task", "ball_on_plate"])
    assert (cfg.env.reward.distance, cfg.num_train_paths, cfg.ppo.num_timesteps) == (4.0, 0, RECIPES["paper"]["num_timesteps"])
    _, cfg = cli.parse_args(["--preset", "paper", "--dataset", "target_point"])
    assert (cfg.env.reward.distance, cfg.num_train_paths) == (TrainConfig().env.reward.distance, 0)
    assert args.out == "runs/armar6_random_paper"
    with pytest.raises(SystemExit):
        cli.parse_args(["--preset", "fastest"])
    assert cli.parse_args(["--final-noise-std", "none"])[1].network.final_noise_std is None  # learned std (Brax's way)
    assert cli.parse_args(["--mean-clip", "1"])[1].network.mean_clip == 1.0


def test_mean_clip_bounds_the_policy_mean():
    from brax.training.acme import running_statistics, specs
    from brax.training.agents.ppo import networks as ppo_nets

    from mjx_pathtrack.deploy.networks import networks as ppo_networks

    obs = jax.random.uniform(jax.random.PRNGKey(1), (64, 10), minval=-1, maxval=1)
    norm = running_statistics.init_state(specs.Array((10,), np.dtype("float32")))
    means = {}
    for clip in (None, 1.0):  # a mean head initialised far too large: only the bound keeps it inside (-1, 1)
        config = TrainConfig().replace(policy_layers=(16,), value_layers=(8,), mean_init_scale=30.0, mean_clip=clip)
        nets = ppo_networks(config.network)(10, 3, preprocess_observations_fn=running_statistics.normalize)
        params = (norm, nets.policy_network.init(jax.random.PRNGKey(0)))
        means[clip] = np.asarray(ppo_nets.make_inference_fn(nets)(params, deterministic=True)(obs, None)[0])
    assert np.abs(means[None]).max() > 2.0
    assert np.abs(means[1.0]).max() < 1.0
    np.testing.assert_allclose(means[1.0], means[None] / (1.0 + np.abs(means[None])), rtol=1e-5, atol=1e-6)


def test_a_privileged_value_network_sees_the_critic_features_and_the_policy_does_not():
    """``privileged_critic``: the policy's action is the same for the plain observation and for
    any critic features appended to it, and uses only the statistics of the plain part; the
    value network's input has the 3 features more and its value depends on them."""
    from brax.training.acme import running_statistics, specs
    from brax.training.agents.ppo import networks as ppo_nets

    from mjx_pathtrack.rl import ppo
    from mjx_pathtrack.deploy.networks import networks as ppo_networks

    config = TrainConfig().replace(policy_layers=(16,), value_layers=(8,), mean_init_scale=1.0, privileged_critic=True)
    nets = ppo_networks(config.network)(10, 3, preprocess_observations_fn=running_statistics.normalize)
    k = jax.random.split(jax.random.PRNGKey(2), 4)
    batch = jax.random.uniform(k[0], (64, 10 + ppo.CRITIC_FEATURES), minval=-1, maxval=1) * 3.0 + 0.5
    norm = running_statistics.update(running_statistics.init_state(specs.Array((13,), np.dtype("float32"))), batch)
    params = (norm, nets.policy_network.init(k[1]), nets.value_network.init(k[2]))
    policy = ppo_nets.make_inference_fn(nets)(params, deterministic=True)
    plain = np.asarray(policy(batch[:, :10], None)[0])
    np.testing.assert_array_equal(plain, np.asarray(policy(batch, None)[0]))
    other = batch.at[:, 10:].set(jax.random.normal(k[3], (64, 3)) * 5.0)
    np.testing.assert_array_equal(plain, np.asarray(policy(other, None)[0]))
    # the policy normalises with the statistics of its own 10 inputs: the same as a plain network
    plain_nets = ppo_networks(TrainConfig().replace(policy_layers=(16,), value_layers=(8,), mean_init_scale=1.0).network)(
        10, 3, preprocess_observations_fn=running_statistics.normalize)
    norm10 = running_statistics.update(running_statistics.init_state(specs.Array((10,), np.dtype("float32"))),
                                       batch[:, :10])
    reference = ppo_nets.make_inference_fn(plain_nets)((norm10, params[1]), deterministic=True)(batch[:, :10], None)[0]
    np.testing.assert_allclose(plain, np.asarray(reference), rtol=1e-5, atol=1e-6)
    value = nets.value_network.apply(norm, params[2], batch)
    assert value.shape == (64,)
    assert not np.allclose(np.asarray(value), np.asarray(nets.value_network.apply(norm, params[2], other)))
    with pytest.raises(Exception):  # the value network needs the features
        nets.value_network.apply(norm, params[2], batch[:, :10])


def test_critic_features_show_the_budget_the_path_left_and_braking():
    from mjx_pathtrack.envs.wrappers import CriticFeatures

    config = TrainConfig().replace(**TINY)
    env = make_env(config, "train")
    wrapped = CriticFeatures(env)
    assert wrapped.observation_size == env.observation_size + 3
    state = jax.jit(wrapped.reset)(jax.random.PRNGKey(3))
    track = state.pipeline_state
    np.testing.assert_array_equal(np.asarray(state.obs[:env.observation_size]), np.asarray(jax.jit(env.observe)(track)))
    path = env.reference(track)
    horizon = env.config.max_episode_steps()
    np.testing.assert_allclose(np.asarray(state.obs[env.observation_size:]),
                               [float(track.max_steps) / horizon,
                                float(path.length - track.s) / (env.config.n_next * env.max_dis), 0.0], rtol=1e-6)
    step = jax.jit(wrapped.step)
    for _ in range(3):
        state = step(state, jnp.ones(env.action_size))
    budget_left = state.obs[env.observation_size]
    assert float(budget_left) == pytest.approx(float(track.max_steps - 3) / horizon, rel=1e-6)
    assert float(state.obs[env.observation_size + 1]) < float(path.length - track.s) / (env.config.n_next * env.max_dis)
    braking = state.pipeline_state._replace(braking=jnp.ones((), bool))
    assert float(env.critic_features(braking)[2]) == 1.0


def test_evaluation_loads_a_checkpoint_of_a_run(tiny_run):
    """``evaluate.py RUN --checkpoint latest|STEP``: a checkpoint's policy (here the last one, whose
    parameters the finished run wrote to params.msgpack: the same actions); bad requests are refused
    by name."""
    from mjx_pathtrack.evaluation.report import EvaluationError, load_policy_source

    out, config, _, _ = tiny_run
    steps = run_dir.checkpoint_steps(out / "checkpoints")
    obs = jax.random.uniform(jax.random.PRNGKey(7), (16, 94), minval=-1, maxval=1)
    final = np.asarray(load_policy_source(str(out)).policy(obs, jax.random.PRNGKey(0)))
    for which in ("latest", str(steps[-1])):
        got = np.asarray(load_policy_source(str(out), checkpoint=which).policy(obs, jax.random.PRNGKey(0)))
        np.testing.assert_array_equal(got, final)
    with pytest.raises(EvaluationError, match=r"no checkpoint of step 1 \(there are: \["):
        load_policy_source(str(out), checkpoint="1")
    with pytest.raises(EvaluationError, match="'latest' or a step"):
        load_policy_source(str(out), checkpoint="newest")
    with pytest.raises(EvaluationError, match="is an export; --checkpoint needs the run directory"):
        load_policy_source(str(out / "export"), checkpoint="latest")


def test_a_run_with_a_privileged_critic_exports_the_plain_policy(tmp_path):
    """Trained with the critic features, the run's parameters and its export act on the plain
    94-value observation and agree."""
    from mjx_pathtrack.evaluation.report import load_policy_source

    config = TrainConfig.from_flat({**TINY, "privileged_critic": True})
    _, params, report = train(config, tmp_path / "run", verbose=False)
    assert np.asarray(params[0].mean).shape == (94 + 3,)  # statistics of the critic's input
    assert np.isfinite(report["after"]["return"])
    exported = load_policy(tmp_path / "run" / "export")
    assert exported.observation_size == 94
    obs = np.asarray(jax.random.uniform(jax.random.PRNGKey(5), (16, 94), minval=-1, maxval=1))
    from_run = load_policy_source(str(tmp_path / "run")).policy
    actions = np.clip(np.asarray(from_run(jnp.asarray(obs), jax.random.PRNGKey(0))), -1, 1)
    np.testing.assert_allclose(actions, exported(obs), rtol=1e-5, atol=1e-6)


def test_noise_std_schedule_is_geometric_from_the_initial_to_the_final_std():
    from mjx_pathtrack.rl import ppo

    config = TrainConfig().replace(init_noise_std=0.5, final_noise_std=0.05)
    stds = [float(ppo.noise_std(config.network, f)) for f in (0.0, 0.5, 1.0, 1.5)]
    np.testing.assert_allclose(stds, [0.5, np.sqrt(0.5 * 0.05), 0.05, 0.05], rtol=1e-5)
    assert ppo.noise_std(TrainConfig().replace(final_noise_std=None).network, 0.3) is None  # learned std: no schedule


@pytest.mark.slow
def test_learning_rate_schedule_is_geometric_and_scales_the_update():
    """``final_learning_rate``: geometric from the rate to the final one (constant when unset); the
    iteration's step scales with it: at scale 0 the parameters do not move, at 1 they do."""
    from mjx_pathtrack.rl import ppo

    config = TrainConfig().replace(learning_rate=1e-3, final_learning_rate=1e-5)
    scales = [float(ppo.learning_rate_scale(config.ppo, f)) for f in (0.0, 0.5, 1.0, 1.5)]
    np.testing.assert_allclose(scales, [1.0, 0.1, 0.01, 0.01], rtol=1e-5)
    assert float(ppo.learning_rate_scale(TrainConfig().replace(final_learning_rate=None).ppo, 0.7)) == 1.0

    tiny = TrainConfig.from_flat({**TINY, "final_noise_std": None})
    core = ppo.build(tiny, make_env(tiny, "train"))
    weights = jnp.asarray(ppo.reward_weights(tiny))
    learner = core.init(0, weights, tiny.ppo.num_envs)
    step = jax.jit(lambda learner, scale: core.iteration(weights, learner, None, scale)[0].params)
    frozen, moved = step(learner, jnp.float32(0.0)), step(learner, jnp.float32(1.0))
    same = jax.tree.map(lambda a, b: bool(np.array_equal(a, b)), frozen, learner.params)
    assert all(jax.tree.leaves(same))
    changed = jax.tree.map(lambda a, b: bool(np.array_equal(a, b)), moved, learner.params)
    assert not all(jax.tree.leaves(changed))


@pytest.mark.slow
def test_a_scheduled_std_is_not_learned_and_ends_at_the_schedule(tmp_path):
    """The std the run ends with is the schedule's value at the start of the last iteration (not
    what Adam would have made of it), in the exported policy's parameters too."""
    from mjx_pathtrack.rl import ppo

    config = TrainConfig.from_flat({**TINY, "num_timesteps": 1280, "final_noise_std": 0.1})
    _, params, _ = train(config, tmp_path / "run", verbose=False)
    log_std = np.asarray(params[1]["params"]["std_logparam"]["log_value"])
    iterations = 1280 // (8 * 5 * 2)
    expected = float(ppo.noise_std(config.network, (iterations - 1) / iterations))
    np.testing.assert_allclose(np.exp(log_std), expected, rtol=1e-5)
    assert expected < 0.5


def test_noise_factors_scale_the_joints_each_prefix_names_first_match_wins():
    from mjx_pathtrack.deploy.networks import noise_factors

    names = ("leg_hip_r", "leg_knee_r", "torso_yaw", "arm_sho1_r", "leg_ankle_r")
    np.testing.assert_allclose(noise_factors(("leg_knee=0.1", "leg_=0.2", "torso=0.5"), names),
                               [0.2, 0.1, 0.5, 1.0, 0.2])
    np.testing.assert_allclose(noise_factors((), names), np.ones(5))
    for bad, match in (("leg_", "PREFIX=FACTOR"), ("=0.2", "PREFIX=FACTOR"), ("leg_=0", "factor > 0"),
                       ("leg_=-1", "factor > 0"), ("leg_=inf", "factor > 0"), ("leg_=x", "factor > 0"),
                       ("foot_=0.5", "no action joint starts with 'foot_'")):
        with pytest.raises(ValueError, match=match):
            noise_factors((bad,), names)


def test_noise_scale_option_from_the_command_line_and_its_errors(tmp_path):
    import train as cli
    from mjx_pathtrack.config.run import ConfigError, validate_config

    _, cfg = cli.parse_args(["--noise-scale", "iiwa_joint_1=0.2", "iiwa_joint_7=0.5"])
    assert cfg.network.noise_scale == ("iiwa_joint_1=0.2", "iiwa_joint_7=0.5")
    assert cli.parse_args([])[1].network.noise_scale == ()
    assert TrainConfig.from_json(cfg.to_json()) == cfg
    with pytest.raises(ConfigError, match="--noise-scale: noise scale 'iiwa_joint_1:0.2'"):
        validate_config(cfg.replace(noise_scale=("iiwa_joint_1:0.2",)))
    with pytest.raises(ConfigError, match="--noise-scale: scales the scheduled std"):
        validate_config(cfg.replace(final_noise_std=None))
    # a prefix that names no joint of the robot: refused before training, nothing left behind
    config = TrainConfig.from_flat({**TINY, "noise_scale": ["leg_=0.2"]})
    with pytest.raises(ValueError, match="no action joint starts with 'leg_'"):
        train(config, tmp_path / "run", verbose=False)
    assert not (tmp_path / "run").exists()


@pytest.mark.slow
def test_noise_scale_multiplies_the_scheduled_std_of_the_named_joints(tmp_path):
    """The run ends with the schedule's std times each joint's factor (the others unscaled), in
    the saved parameters that the sampled policy uses."""
    from mjx_pathtrack.rl import ppo

    config = TrainConfig.from_flat({**TINY, "num_timesteps": 1280, "final_noise_std": 0.1,
                                    "noise_scale": ["iiwa_joint_2=0.25", "iiwa_joint_=0.5"]})
    _, params, _ = train(config, tmp_path / "run", verbose=False)
    std = np.exp(np.asarray(params[1]["params"]["std_logparam"]["log_value"]))
    iterations = 1280 // (8 * 5 * 2)
    expected = float(ppo.noise_std(config.network, (iterations - 1) / iterations))
    np.testing.assert_allclose(std, expected * np.array([0.5, 0.25, 0.5, 0.5, 0.5, 0.5, 0.5]), rtol=1e-5)


# --- exact resume, run-directory safety, clear errors (issue: safety and data) -----------------

EXACT = {**TINY, "num_evals": 4}


@pytest.mark.slow
def test_resume_after_sigkill_ends_with_the_parameters_of_an_uninterrupted_run(tmp_path):
    """A CLI run killed (SIGKILL) after logging step 2 of 3 but before that checkpoint, then
    resumed with --resume: parameters bit for bit those of an uninterrupted run, progress.csv
    without repeated steps, wall_s still increasing. (The child keeps this process's XLA flags
    as its own, so both compile the same programs.)"""
    reference = tmp_path / "reference"
    _, params, _ = train(TrainConfig().replace(**EXACT), reference, verbose=False)
    run = tmp_path / "killed"
    env = dict(os.environ, XLA_FLAGS=os.environ.get("XLA_FLAGS", ""))
    env.pop("MJX_PATHTRACK_ADDED_XLA_FLAG", None)  # the flag counts as the user's: train.py keeps it
    steps = sorted(int(r["step"]) for r in csv.DictReader(open(reference / "progress.csv")))
    # the child is train.py whose checkpoint writer kills the process (SIGKILL) at step 2, after
    # that step's progress is logged and before its checkpoint is written: the worst moment for a
    # resume, the log ahead of the last checkpoint (patched here: no test hook in the training loop)
    child = ("import os, signal, sys\n"
             "import mjx_pathtrack.rl.training as T\n"
             "save = T.save_checkpoint\n"
             "def save_or_die(directory, step, data, *a, **k):\n"
             f"    if step >= {steps[2]}:\n"
             "        os.kill(os.getpid(), signal.SIGKILL)\n"
             "    return save(directory, step, data, *a, **k)\n"
             "T.save_checkpoint = save_or_die\n"
             "sys.argv = ['train.py', *sys.argv[1:]]\n"
             "import runpy\n"
             "runpy.run_path('train.py', run_name='__main__')\n")
    killed = subprocess.run([sys.executable, "-c", child, *tiny_args(run), "--num-evals", "4"], cwd=REPO,
                            env=env, capture_output=True, text=True, timeout=900)
    assert killed.returncode == -9, killed.stderr[-2000:]
    assert latest_checkpoint(run / "checkpoints")[1] == steps[1] and not (run / "params.msgpack").exists()
    assert max(int(r["step"]) for r in csv.DictReader(open(run / "progress.csv"))) == steps[2]  # log ahead
    _, resumed, _ = train(TrainConfig().replace(**EXACT), run, resume=True, verbose=False)
    for a, b in zip(jax.tree.leaves(params), jax.tree.leaves(resumed)):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
    rows = list(csv.DictReader(open(run / "progress.csv")))
    assert [int(r["step"]) for r in rows] == steps
    walls = [float(r["wall_s"]) for r in rows]
    assert walls == sorted(walls)


def test_a_run_directory_holding_a_run_is_refused_and_left_untouched(tiny_run, tmp_path):
    from mjx_pathtrack.config.run_dir import RunDirError

    out, config, _, _ = tiny_run
    run = tmp_path / "run"
    subprocess.run(["cp", "-r", str(out), str(run)], check=True)
    before = {p.relative_to(run): p.read_bytes() for p in run.rglob("*") if p.is_file()}
    with pytest.raises(RunDirError, match="holds a training run .*--resume .*--overwrite"):
        train(config, run, verbose=False)
    with pytest.raises(RunDirError, match="exclude each other"):
        train(config, run, resume=True, overwrite=True, verbose=False)
    # a failing option is refused before anything is written, even with --resume
    from mjx_pathtrack.config.run import ConfigError

    with pytest.raises(ConfigError, match="--batch-size"):
        train(TrainConfig.from_flat({**TINY, "num_envs": 15, "batch_size": 16}), run, resume=True, verbose=False)
    after = {p.relative_to(run): p.read_bytes() for p in run.rglob("*") if p.is_file()}
    assert after == before


def test_overwrite_replaces_the_run_and_a_new_directory_is_removed_when_nothing_was_trained(tmp_path, monkeypatch):
    from mjx_pathtrack.rl import training

    run = tmp_path / "run"
    run.mkdir()
    (run / "params.msgpack").write_bytes(b"old")
    (run / "params.pkl").write_bytes(b"older")
    (run / "notes.txt").write_text("mine")
    run_dir.clear_run_dir(run)
    assert not (run / "params.msgpack").exists() and not (run / "params.pkl").exists() and (run / "notes.txt").read_text() == "mine"  # only our files

    def broken(*args, **kwargs):
        raise RuntimeError("boom")

    monkeypatch.setattr(training, "_train", broken)
    new = tmp_path / "new"
    with pytest.raises(RuntimeError, match="boom"):
        train(TrainConfig().replace(**TINY), new, verbose=False)
    assert not new.exists()


def test_non_finite_parameters_stop_the_run_and_keep_the_last_good_checkpoint(tmp_path, monkeypatch):
    from mjx_pathtrack.rl import training

    real = training._program

    def poisoned(config, env, joint_names=None):
        program = real(config, env, joint_names)
        calls = []

        def epoch(learner, start, end):
            learner, summary = program.epoch(learner, start, end)
            calls.append(1)
            if len(calls) == 2:  # the second interval diverges
                learner = learner._replace(params=jax.tree.map(lambda x: x * np.nan, learner.params))
            return learner, summary

        return program._replace(epoch=epoch)

    monkeypatch.setattr(training, "_program", poisoned)
    run = tmp_path / "run"
    with pytest.raises(training.TrainingDiverged, match="diverged between steps .*last good checkpoint is .*ckpt"):
        train(TrainConfig().replace(**EXACT), run, verbose=False)
    path, step = latest_checkpoint(run / "checkpoints")
    state = run_dir.load_checkpoint(path)
    assert state["step"] == step and all(np.all(np.isfinite(x)) for x in jax.tree.leaves(state["params"]))
    assert not (run / "params.msgpack").exists() and not (run / "export").exists()


@pytest.mark.parametrize("argv,message", [
    (["--num-envs", "-16"], "--num-envs: must be >= 1"),
    (["--num-envs", "15", "--batch-size", "16"], "--batch-size: batch_size \\* num_minibatches .* multiple of --num-envs"),
    (["--dt", "0"], "--dt: must be a finite number > 0"),
    (["--alpha", "nan"], "--alpha: must be a finite number >= 0"),
    (["--learning-rate", "inf"], "--learning-rate: must be a finite number > 0"),
    (["--dataset", "spirals"], "--dataset: no dataset config .*datasets of iiwa: .*random"),
    (["--executor", "mjx", "--dt", "0.11"], "--dt: 0.11 s must be a whole multiple of the physics step"),
    (["--substeps", "0"], "--substeps: must be >= 1"),
    (["--task", "ball_on_plate", "--substeps", "12"], "--substeps: with MJX physics .* 24 at --dt 0.1, got 12"),
    (["--gae-lambda", "1.5"], "--gae-lambda: must be in"),
    (["--final-noise-std", "0"], "--final-noise-std: must be a finite number > 0"),
    (["--final-learning-rate", "0"], "--final-learning-rate: must be a finite number > 0"),
    (["--end-knot-tolerance", "0"], "--end-knot-tolerance: must be a finite number > 0"),
    (["--leg-prior", "hold"], "--leg-prior: 'hold' adds to the policy's leg actions: it needs --task balance --legs controlled"),
    (["--task", "balance", "--legs", "fixed", "--leg-prior", "hold"], "--leg-prior: .*needs --task balance --legs controlled"),
])
def test_bad_options_are_one_line_errors_naming_the_option(argv, message):
    import train as cli
    from mjx_pathtrack.config.run import ConfigError, validate_config

    with pytest.raises(ConfigError, match=message) as e:  # (a block's own check fails already in parse_args)
        validate_config(cli.parse_args(argv)[1])
    assert "\n" not in str(e.value)


def test_unknown_robot_and_bad_out_are_clear_cli_errors(tmp_path):
    """The command line: rc 2 and one line on stderr, before any compiling (a few seconds)."""
    blocker = tmp_path / "a_file"
    blocker.write_text("")
    for argv, message in ((["--robot", "r2d2"], "--robot: unknown robot 'r2d2'"),
                          (["--out", str(blocker)], f"--out {blocker}: is a file"),
                          (["--out", str(blocker / "run")], "cannot create or write it")):
        result = subprocess.run([sys.executable, "train.py", *argv], cwd=REPO, capture_output=True, text=True,
                                timeout=300)
        assert result.returncode == 2, result.stderr[-2000:]
        assert message in result.stderr and "Traceback" not in result.stderr
        assert "Failed to import" not in result.stdout  # mujoco.mjx's Warp notices are silenced


def test_observe_deviation_option_and_its_task_check():
    """``--observe-deviation`` and ``--observe-speed-limits`` reach the environment config and round-trips through config.json;
    a task other than tracking is refused naming the option."""
    import train as cli
    from mjx_pathtrack.config.run import ConfigError, validate_config

    _, cfg = cli.parse_args(["--observe-deviation"])
    assert cfg.env.observe_deviation and not cli.parse_args([])[1].env.observe_deviation
    assert TrainConfig.from_json(cfg.to_json()) == cfg
    with pytest.raises(ConfigError, match="--observe-deviation: the deviation block is built for the tracking task"):
        validate_config(cli.parse_args(["--task", "ball_on_plate", "--observe-deviation"])[1])
    _, cfg = cli.parse_args(["--observe-speed-limits"])
    assert cfg.env.observe_speed_limits and not cli.parse_args([])[1].env.observe_speed_limits
    assert TrainConfig.from_json(cfg.to_json()) == cfg
    with pytest.raises(ConfigError, match="--observe-speed-limits: the speed-limit block is built for the tracking task"):
        validate_config(cli.parse_args(["--task", "balance", "--observe-speed-limits"])[1])
