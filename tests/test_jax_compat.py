"""_jax_compat.device_put_replicated: the drop-in for the function JAX 0.10 removed."""

import jax
import jax.numpy as jnp
import numpy as np

from mjx_pathtrack import _jax_compat


def test_device_put_replicated_stacks_one_copy_per_device():
    devices = jax.local_devices()
    tree = {"w": jnp.arange(6.0).reshape(2, 3), "b": np.float32(1.5)}
    out = _jax_compat.device_put_replicated(tree, devices)
    assert out["w"].shape == (len(devices), 2, 3)
    assert out["b"].shape == (len(devices),)
    np.testing.assert_array_equal(np.asarray(out["w"][0]), np.arange(6.0).reshape(2, 3))
    # pmap consumes it the way brax does (leading axis = devices).
    summed = jax.pmap(lambda t: t["w"].sum() + t["b"])(out)
    np.testing.assert_allclose(np.asarray(summed), np.full(len(devices), 16.5))


def test_install_is_noop_when_jax_has_it():
    has_native = _jax_compat._has("device_put_replicated")
    before = getattr(jax, "device_put_replicated", None) if has_native else None
    added = _jax_compat.install()
    assert added is (not has_native)
    assert _jax_compat._has("device_put_replicated")
    if has_native:
        assert jax.device_put_replicated is before
