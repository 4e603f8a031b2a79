"""ONNX policy graphs: conversion of a jitted function, running them, clear errors."""

import numpy as np
import pytest

import mjx_pathtrack  # noqa: F401
import jax.numpy as jnp

from mjx_pathtrack.deploy import onnx_policy as O


def _policy(obs):   # a small fixed "network": tanh of an affine map, clipped like the export
    w = jnp.asarray(np.random.default_rng(0).normal(size=(5, 3)), jnp.float32)
    return jnp.clip(2.0 * jnp.tanh(obs @ w + 0.1), -1.0, 1.0)


def test_a_jitted_function_converts_with_named_io_and_any_batch():
    model = O.policy_to_onnx(_policy, 5)
    policy = O.OnnxPolicy(model)
    assert policy.observation_size == 5
    for batch in (1, 7, 300):
        obs = np.random.default_rng(batch).uniform(-1, 1, (batch, 5)).astype(np.float32)
        np.testing.assert_allclose(policy(obs), np.asarray(_policy(jnp.asarray(obs))), atol=1e-6, rtol=0)
    assert O.max_difference(policy, lambda o: np.asarray(_policy(jnp.asarray(o))), count=1000) <= 1e-6
    # a different reference is seen as different
    assert O.max_difference(policy, lambda o: np.zeros((len(o), 3), np.float32), count=100) > 0.1


def test_check_observations_cover_the_corners_of_the_observation_range():
    obs = O.check_observations(6, 50, seed=3)
    assert obs.shape == (50, 6) and obs.dtype == np.float32
    assert np.all(np.abs(obs) <= 1.0)
    np.testing.assert_array_equal(obs[0], np.ones(6))
    np.testing.assert_array_equal(obs[1], -np.ones(6))
    np.testing.assert_array_equal(O.check_observations(6, 50, seed=3), obs)


def test_bad_onnx_files_and_inputs_give_clear_errors(tmp_path):
    policy = O.OnnxPolicy(O.policy_to_onnx(_policy, 5))
    with pytest.raises(O.OnnxError, match=r"shape \[5\] or \[B, 5\]"):
        policy(np.zeros((2, 4), np.float32))
    with pytest.raises(O.OnnxError, match="no ONNX policy"):
        O.OnnxPolicy(tmp_path / "missing.onnx")
    (tmp_path / "broken.onnx").write_bytes(b"not a protobuf")
    with pytest.raises(O.OnnxError, match="corrupt"):
        O.OnnxPolicy(tmp_path / "broken.onnx")
    from jax2onnx import to_onnx

    other = to_onnx(_policy, [("batch", 5)], model_name="other").SerializeToString()   # jax2onnx's own names
    with pytest.raises(O.OnnxError, match="not a policy graph"):
        O.OnnxPolicy(other)
