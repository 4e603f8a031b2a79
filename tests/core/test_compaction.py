"""Tests of mjx_pathtrack.core.compaction: the compacted function equals the plain one, lane by lane,
and runs only as many chunks as the needing lanes fill."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from mjx_pathtrack.core import compaction as C


def _fn(x, y):
    """An elementwise function with a pytree output and a loop inside (like the position search)."""
    z = jax.lax.fori_loop(0, 3, lambda _, z: jnp.sqrt(z * z + y), x)
    return z * y, z > y


def _reference(need, x, y, fill=0.0):
    z, flag = _fn(*jnp.broadcast_arrays(x, y))
    return jnp.where(need, z, fill), jnp.where(need, flag, bool(fill))  # fill cast to each output's dtype


def _assert_same(a, b):
    for u, w in zip(jax.tree.leaves(a), jax.tree.leaves(b)):
        assert u.shape == w.shape and u.dtype == w.dtype
        np.testing.assert_array_equal(np.asarray(u), np.asarray(w))


@pytest.mark.parametrize("share", [0.0, 0.03, 0.5, 1.0])
def test_where_needed_equals_the_plain_function_on_needed_lanes(share):
    rng = np.random.default_rng(0)
    x = jnp.asarray(rng.uniform(0, 2, (6, 300)), jnp.float32)
    y = jnp.asarray(rng.uniform(0, 1, (300,)), jnp.float32)  # broadcast against x
    need = jnp.asarray(rng.uniform(size=x.shape) < share)
    want = _reference(need, x, y, fill=-1.0)
    _assert_same(C.where_needed(_fn, need, x, y, fill=-1.0), want)
    _assert_same(jax.jit(lambda n, x, y: C.where_needed(_fn, n, x, y, fill=-1.0))(need, x, y), want)
    # vmapped (compacted across the batch), with an unbatched argument, and nested
    per_row = jax.vmap(lambda n, x, y: C.where_needed(_fn, n, x, y, fill=-1.0), in_axes=(0, 0, None))
    _assert_same(jax.jit(per_row)(need, x, y), want)
    per_lane = jax.vmap(jax.vmap(lambda n, x, y: C.where_needed(_fn, n, x, y, fill=-1.0)), in_axes=(0, 0, None))
    _assert_same(jax.jit(per_lane)(need, x, y), want)


def test_scalar_lanes_under_vmap_with_a_scalar_argument():
    x = jnp.linspace(0.0, 3.0, 50, dtype=jnp.float32)
    out = jax.vmap(lambda x: C.where_needed(lambda x, c: x * c, x > 1.0, x, 2.0))(x)
    np.testing.assert_array_equal(np.asarray(out), np.where(np.asarray(x) > 1.0, 2.0 * np.asarray(x), 0.0))


@pytest.mark.parametrize("n_needed", [0, 1, 128, 129, 700])
def test_runs_one_call_per_chunk_of_needing_lanes(n_needed):
    """The saving is real: with 2048 lanes (chunks of 128) the function runs ceil(k / 128)
    times on 128 lanes, not once on all lanes; also when the lanes come from a vmap."""
    calls = []

    def fn(x):
        jax.debug.callback(lambda shape: calls.append(int(shape)), x.shape[0])
        return x + 1.0

    x = jnp.arange(2048, dtype=jnp.float32).reshape(64, 32)
    need = jnp.zeros(2048, bool).at[(np.arange(n_needed) * 7919) % 2048].set(True).reshape(64, 32)
    assert C.chunk_size(2048) == 128
    for run in (jax.jit(lambda n, x: C.where_needed(fn, n, x)),
                jax.jit(jax.vmap(lambda n, x: C.where_needed(fn, n, x)))):
        calls.clear()
        out = jax.block_until_ready(run(need, x))
        np.testing.assert_array_equal(np.asarray(out), np.where(np.asarray(need), np.asarray(x) + 1.0, 0.0))
        assert calls == [128] * -(-n_needed // 128)


def test_chunk_size_grows_with_the_batch():
    assert C.chunk_size(10) == 10
    assert C.chunk_size(128) == 128
    assert C.chunk_size(2048) == 128
    assert C.chunk_size(12288) == 768


def test_eager_calls_run_on_every_lane_without_a_loop():
    """Outside jit a compiled loop would be rebuilt on every call: the function then runs on all
    lanes once (and the result is the same)."""
    calls = []

    def fn(x):
        calls.append(x.shape)
        return x * 2.0

    x = jnp.arange(300, dtype=jnp.float32)
    out = C.where_needed(fn, x > 100, x)
    np.testing.assert_array_equal(np.asarray(out), np.where(np.asarray(x) > 100, 2.0 * np.asarray(x), 0.0))
    assert calls == [(300,)]
