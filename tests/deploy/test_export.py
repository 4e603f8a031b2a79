"""Exported policy: round trip equals the in-process policy; clear errors for bad exports."""

import json
import subprocess
import sys

import numpy as np
import pytest

import mjx_pathtrack  # noqa: F401
import jax
import jax.numpy as jnp
from brax.training.acme import running_statistics, specs
from brax.training.agents.ppo import networks as ppo_networks

from mjx_pathtrack.robots import iiwa
from mjx_pathtrack.envs.tracking import EnvConfig, PathTrackingEnv
from mjx_pathtrack.deploy.export import ExportError, export_policy, load_policy
from mjx_pathtrack.config.run import TrainConfig
from mjx_pathtrack.deploy.networks import networks as ppo_networks_factory
from path_fixtures import random_walk_paths


@pytest.fixture(scope="module")
def exported(tmp_path_factory):
    env = PathTrackingEnv(iiwa.joint_limits(0.1), random_walk_paths(n_paths=2), 0.5, EnvConfig())
    # the network family training uses, with a mean head initialised large enough that some
    # actions fall outside [-1, 1] (the export clips them like the environment does)
    factory = ppo_networks_factory(TrainConfig().replace(policy_layers=(32, 16), value_layers=(8,), mean_init_scale=3.0).network)
    nets = factory(env.observation_size, env.action_size, preprocess_observations_fn=running_statistics.normalize)
    make_inference_fn = ppo_networks.make_inference_fn(nets)
    key = jax.random.PRNGKey(0)
    normalizer = running_statistics.init_state(specs.Array((env.observation_size,), jnp.dtype("float32")))
    # non-trivial observation statistics, so that the export must carry the normalisation
    normalizer = normalizer.replace(mean=jax.random.normal(key, normalizer.mean.shape) * 0.3,
                                    std=jax.random.uniform(key, normalizer.std.shape, minval=0.2, maxval=2.0))
    params = (normalizer, nets.policy_network.init(key))
    out = export_policy(tmp_path_factory.mktemp("export") / "policy", make_inference_fn, params, env, "iiwa",
                        iiwa.JOINT_NAMES)
    return out, make_inference_fn(params, deterministic=True), env


def test_round_trip_matches_in_process_policy(exported):
    out, inference, env = exported
    policy = load_policy(out)
    obs = np.random.default_rng(0).uniform(-1, 1, (33, env.observation_size)).astype(np.float32)
    raw = np.asarray(inference(jnp.asarray(obs), jax.random.PRNGKey(5))[0])
    assert np.abs(raw).max() > 1.0  # the clipping below is exercised
    expected = np.clip(raw, -1.0, 1.0)
    np.testing.assert_allclose(policy(obs), expected, atol=1e-6)
    np.testing.assert_allclose(policy(obs[0]), expected[0], atol=1e-6)  # single observation
    manifest = policy.manifest
    assert manifest["robot"] == "iiwa" and manifest["task"] == "tracking"
    assert manifest["joint_names"] == list(iiwa.JOINT_NAMES)
    assert manifest["observation_size"] == 94 and manifest["action_size"] == 7
    assert sum(block["size"] for block in manifest["observation_layout"]) == 94


def test_load_needs_neither_brax_nor_flax(exported):
    out, _, env = exported
    code = (f"import sys; sys.modules['brax'] = None; sys.modules['flax'] = None\n"
            f"import numpy as np\nfrom mjx_pathtrack.deploy.export import load_policy\n"
            f"p = load_policy({str(out)!r})\nprint(p(np.zeros({env.observation_size}, np.float32)).shape)")
    result = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300)
    assert result.returncode == 0, result.stderr[-2000:]
    assert result.stdout.strip().endswith("(7,)")


def test_bad_exports_and_inputs_give_clear_errors(exported, tmp_path):
    out, _, _ = exported
    policy = load_policy(out)
    with pytest.raises(ExportError, match="shape"):
        policy(np.zeros((2, 93), np.float32))
    with pytest.raises(ExportError, match="NaN"):
        policy(np.full(94, np.nan, np.float32))
    with pytest.raises(ExportError, match="missing"):
        load_policy(tmp_path / "nothing")
    broken = tmp_path / "broken"
    broken.mkdir()
    (broken / "manifest.json").write_text((out / "manifest.json").read_text())
    (broken / "policy.jaxexport").write_bytes(b"not a flatbuffer")
    with pytest.raises(ExportError, match="corrupt"):
        load_policy(broken)
    manifest = json.loads((out / "manifest.json").read_text())
    (broken / "manifest.json").write_text(json.dumps({**manifest, "format_version": 99}))
    with pytest.raises(ExportError, match="version"):
        load_policy(broken)


@pytest.mark.parametrize("content,message", [
    ([], "not a manifest .*list"),
    ("policy", "not a manifest .*str"),
    ({"format_version": 1}, "key 'robot' is missing"),
    ("drop:observation_size", "key 'observation_size' is missing, must be an integer"),
    ("set:dt=fast", "key 'dt' is 'fast', must be a number"),
])
def test_manifest_that_is_json_but_not_a_manifest_is_an_export_error(exported, tmp_path, content, message):
    out, _, _ = exported
    manifest = json.loads((out / "manifest.json").read_text())
    if content == "drop:observation_size":
        content = {k: v for k, v in manifest.items() if k != "observation_size"}
    elif content == "set:dt=fast":
        content = {**manifest, "dt": "fast"}
    bad = tmp_path / "bad"
    bad.mkdir()
    (bad / "manifest.json").write_text(json.dumps(content))
    (bad / "policy.jaxexport").write_bytes((out / "policy.jaxexport").read_bytes())
    with pytest.raises(ExportError, match=message):
        load_policy(bad)


def test_traced_call_leaves_the_mjx_physics_beside_it_unchanged(exported):
    """The export inside a jitted program (as the evaluation rollout runs it) gives the actions of
    a plain call and leaves MJX physics compiled in the same program as it is alone. Calling the
    shape-polymorphic export inline made JAX refine the whole program's shapes, after which the
    servo-controlled iiwa ended a 0.1 s step 0.037 rad from where it ends alone (jax 0.9.2)."""
    from mjx_pathtrack.envs.executors import MjxExecutor
    from mjx_pathtrack.robots import registry

    out, inference, env = exported
    policy = load_policy(out)
    executor = MjxExecutor(registry.load_robot("iiwa", dt=0.1))
    p0, v, a0, a1 = jnp.full(7, 0.3), jnp.full(7, 0.5), jnp.zeros(7), jnp.full(7, 2.0)
    obs = jnp.asarray(np.random.default_rng(1).uniform(-1, 1, (3, env.observation_size)), jnp.float32)

    def step_beside(act):
        @jax.jit
        def program():
            actions = act(obs)
            _, executed, _ = executor.execute(executor.init(p0), p0, v + 0.0 * actions[0], a0, a1, 0.1)
            return actions, executed[-1]
        return program()

    _, alone = step_beside(lambda o: jnp.zeros((o.shape[0], 7)))
    actions, beside = step_beside(policy.traced_call)
    # the in-process network's actions (an independent reference, not the export again)
    expected = np.clip(np.asarray(inference(obs, jax.random.PRNGKey(0))[0]), -1.0, 1.0)
    np.testing.assert_allclose(np.asarray(actions), expected, atol=1e-6)
    np.testing.assert_allclose(np.asarray(beside), np.asarray(alone), atol=1e-6)
    # the servos end the step near the constant-jerk setpoint p0 + v dt + (a1 - a0) dt^2 / 6
    setpoint = p0 + v * 0.1 + (a1 - a0) * 0.1 ** 2 / 6
    assert np.abs(np.asarray(alone) - np.asarray(setpoint)).max() < 1e-3
    with pytest.raises(ExportError, match="shape"):
        policy.traced_call(obs[0])


def test_export_writes_an_onnx_graph_that_agrees_with_the_network(exported):
    """``policy.onnx`` (jax2onnx, observation -> action) gives the in-process network's clipped
    actions within 1e-5 on 10,000 fresh observations, as the manifest's figure claims."""
    from mjx_pathtrack.deploy.onnx_policy import OnnxPolicy

    out, inference, env = exported
    entry = load_policy(out).manifest["onnx"]
    assert entry["file"] == "policy.onnx" and entry["checked_observations"] == 10_000
    assert 0.0 <= entry["max_abs_difference"] <= 1e-5
    onnx = OnnxPolicy(out / "policy.onnx")
    obs = np.random.default_rng(7).uniform(-1, 1, (10_000, env.observation_size)).astype(np.float32)
    raw = np.asarray(inference(jnp.asarray(obs), jax.random.PRNGKey(0))[0])
    assert np.abs(raw).max() > 1.0   # the graph's clipping is exercised
    np.testing.assert_allclose(onnx(obs), np.clip(raw, -1.0, 1.0), atol=1e-5, rtol=0)
    np.testing.assert_allclose(onnx(obs[3]), np.clip(raw[3], -1.0, 1.0), atol=1e-5, rtol=0)


def test_onnx_policy_runs_with_numpy_and_onnxruntime_alone(exported):
    """The README's deployment example: no JAX, no package, only numpy and onnxruntime."""
    out, inference, env = exported
    code = (f"import sys; sys.modules['jax'] = None; sys.modules['mjx_pathtrack'] = None\n"
            f"import numpy as np, onnxruntime as ort\n"
            f"session = ort.InferenceSession({str(out / 'policy.onnx')!r})\n"
            f"obs = np.linspace(-1, 1, 2 * {env.observation_size}, dtype=np.float32).reshape(2, -1)\n"
            f"print(repr(session.run(['action'], {{'observation': obs}})[0].tolist()))")
    result = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300)
    assert result.returncode == 0, result.stderr[-2000:]
    actions = np.array(eval(result.stdout.strip().splitlines()[-1]))
    obs = np.linspace(-1, 1, 2 * env.observation_size, dtype=np.float32).reshape(2, -1)
    expected = np.clip(np.asarray(inference(jnp.asarray(obs), jax.random.PRNGKey(0))[0]), -1.0, 1.0)
    np.testing.assert_allclose(actions, expected, atol=1e-5, rtol=0)


def test_an_onnx_graph_that_disagrees_is_not_written_and_the_manifest_says_why(tmp_path, monkeypatch):
    """A graph off by more than 1e-5 never reaches the export directory; the jax.export policy
    does, with the reason in the manifest. A policy jax2onnx cannot convert: the same."""
    from mjx_pathtrack.deploy import onnx_policy

    env = PathTrackingEnv(iiwa.joint_limits(0.1), random_walk_paths(n_paths=2), 0.5, EnvConfig())
    factory = ppo_networks_factory(TrainConfig().replace(policy_layers=(8,), value_layers=(8,)).network)
    nets = factory(env.observation_size, env.action_size, preprocess_observations_fn=running_statistics.normalize)
    normalizer = running_statistics.init_state(specs.Array((env.observation_size,), jnp.dtype("float32")))
    params = (normalizer, nets.policy_network.init(jax.random.PRNGKey(0)))
    monkeypatch.setattr(onnx_policy, "max_difference", lambda *a, **k: 3e-4)
    out = export_policy(tmp_path / "export", ppo_networks.make_inference_fn(nets), params, env, "iiwa", iiwa.JOINT_NAMES)
    assert not (out / "policy.onnx").exists()
    entry = load_policy(out).manifest["onnx"]
    assert entry["file"] is None and "differs from the jax.export policy by 3.00e-04" in entry["reason"]

    def unconvertible(*args, **kwargs):
        raise onnx_policy.OnnxError("jax2onnx cannot convert this policy: TypeError: a construct")

    monkeypatch.setattr(onnx_policy, "policy_to_onnx", unconvertible)
    out = export_policy(tmp_path / "export2", ppo_networks.make_inference_fn(nets), params, env, "iiwa", iiwa.JOINT_NAMES)
    assert not (out / "policy.onnx").exists()
    assert "cannot convert" in load_policy(out).manifest["onnx"]["reason"]
    from mjx_pathtrack.deploy.export import attach_onnx

    monkeypatch.undo()
    entry = attach_onnx(out, jax.jit(lambda obs: jnp.clip(ppo_networks.make_inference_fn(nets)(params, True)(
        obs, jax.random.PRNGKey(0))[0], -1.0, 1.0)))     # the same network, attached afterwards
    assert (out / "policy.onnx").is_file() and entry["max_abs_difference"] <= 1e-5
    assert load_policy(out).manifest["onnx"] == entry
