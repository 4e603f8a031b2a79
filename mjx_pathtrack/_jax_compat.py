"""Compatibility shims that let the pinned brax 0.14.2 run on newer JAX releases.

The project pins jax 0.9.2 (pyproject.toml), but GPU images often ship a newer JAX
(e.g. 0.11.2). brax 0.14.2's PPO calls ``jax.device_put_replicated``, which JAX 0.10
removed ("use jax.device_put instead"). :func:`install` adds the documented drop-in
replacement (stack ``len(devices)`` copies and shard the leading axis over the devices)
only when JAX lacks the function; on the pinned JAX it changes nothing.
"""

from __future__ import annotations

import warnings
from collections.abc import Sequence
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np


def device_put_replicated(x: Any, devices: Sequence[jax.Device]) -> Any:
    """Pytree ``x`` with a new leading axis of ``len(devices)`` copies, one per device."""
    devices = list(devices)
    mesh = jax.sharding.Mesh(np.array(devices), ("replicas",))
    sharding = jax.sharding.NamedSharding(mesh, jax.sharding.PartitionSpec("replicas"))
    return jax.tree.map(
        lambda leaf: jax.device_put(jnp.stack([jnp.asarray(leaf)] * len(devices)), sharding), x
    )


def _has(name: str) -> bool:
    with warnings.catch_warnings():  # deprecated-but-present names warn on access
        warnings.simplefilter("ignore", DeprecationWarning)
        try:
            getattr(jax, name)
        except AttributeError:  # removed names raise from jax's module __getattr__
            return False
    return True


def install() -> bool:
    """Add the missing JAX functions brax needs; True if anything was added."""
    if _has("device_put_replicated"):
        return False
    jax.device_put_replicated = device_put_replicated
    return True
