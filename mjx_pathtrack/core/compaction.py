"""Run an expensive elementwise function only on the lanes that need it (stream compaction).

Under ``jax.vmap`` every environment computes every branch: a search that only a few percent
of the joints need (a position limit within reach) costs as much as if all needed it.
:func:`where_needed` gathers the lanes that need the function into chunks of a static size,
evaluates the function on those chunks only (a loop whose trip count is the number of chunks
actually needed) and scatters the results back. Under ``vmap`` a ``custom_vmap`` rule applies
the same compaction to the whole batch, so the saving is across environments.

The function must be *elementwise over lanes*: lane ``i`` of the result depends only on lane
``i`` of the arguments. Lanes that do not need it get ``fill``. Called eagerly (outside
``jit``), the function simply runs on every lane.
"""

from __future__ import annotations

from typing import Callable

import jax
import jax.numpy as jnp
import numpy as np

#: a chunk holds at least this many lanes (or all of them) ...
MIN_CHUNK = 128
#: ... and at least this fraction of all lanes (a larger share needs several chunks)
CHUNK_FRACTION = 1.0 / 16.0


def chunk_size(n_lanes: int) -> int:
    """Static number of lanes per chunk for ``n_lanes`` lanes in all."""
    return max(1, min(n_lanes, max(MIN_CHUNK, int(np.ceil(n_lanes * CHUNK_FRACTION)))))


def where_needed(fn: Callable, need, *args, fill: float = 0.0):
    """``fn(*args)`` on the lanes where ``need`` is true, ``fill`` elsewhere (a pytree like ``fn``'s).

    ``need``: bool array; ``args``: arrays broadcastable to ``need.shape``; ``fn`` maps lane
    arrays ``[m]`` to a pytree of arrays ``[m]`` elementwise. Jittable and vmappable (a vmap is
    compacted across the batch). Example: ``where_needed(jnp.sqrt, x > 0, x)``."""
    need = jnp.asarray(need, bool)
    if is_concrete(need, *args):
        return _everywhere(fn, need, args, fill)
    # jitted once here so that its trace is reused (the output shapes and the loop body of
    # _compacted see the same chunk): the search is traced once per chunk size, not twice
    fn = jax.jit(fn)

    @jax.custom_batching.custom_vmap
    def apply(need, *args):
        return _compacted(fn, need, args, fill)

    @apply.def_vmap
    def rule(axis_size, in_batched, need, *args):
        # lift the unbatched arguments to the batch and compact over all of it (an outer vmap
        # calls this rule again with the larger batch)
        batched_need, *batched_args = in_batched
        shape = jnp.broadcast_shapes(need.shape[1:] if batched_need else need.shape,
                                     *(jnp.shape(x)[1:] if b else jnp.shape(x) for x, b in zip(args, batched_args)))
        full = (axis_size,) + tuple(shape)

        def lift(x, batched):
            x = jnp.asarray(x)
            if batched:
                return jnp.broadcast_to(x.reshape(x.shape[:1] + (1,) * (len(shape) - (x.ndim - 1)) + x.shape[1:]), full)
            return jnp.broadcast_to(x, full)

        need, args = lift(need, batched_need), [lift(x, b) for x, b in zip(args, batched_args)]
        out = _everywhere(fn, need, args, fill) if is_concrete(need, *args) else apply(need, *args)
        return out, jax.tree.map(lambda _: True, out)

    return apply(need, *args)


def is_concrete(*xs) -> bool:
    """True outside any trace (eager calls, incl. the rule of an eager ``vmap``)."""
    return not any(isinstance(x, jax.core.Tracer) for x in xs)


def _everywhere(fn, need, args, fill):
    """``fn`` on every lane, ``fill`` where not needed. For eager calls: there the loop of
    :func:`_compacted` would be traced and compiled anew on every call (``fn`` is usually a new
    closure), which costs far more than the lanes it saves."""
    shape = jnp.broadcast_shapes(need.shape, *(jnp.shape(x) for x in args))
    out = fn(*(jnp.broadcast_to(jnp.asarray(x), shape) for x in args))
    return jax.tree.map(lambda r: jnp.where(need, r, jnp.asarray(fill, r.dtype)), out)


def _compacted(fn, need, args, fill):
    """Unbatched compaction over all elements of ``need`` (see :func:`where_needed`)."""
    shape = jnp.broadcast_shapes(need.shape, *(jnp.shape(x) for x in args))
    flat_need = jnp.broadcast_to(need, shape).reshape(-1)
    flat_args = [jnp.broadcast_to(jnp.asarray(x), shape).reshape(-1) for x in args]
    n = flat_need.shape[0]
    if not isinstance(n, (int, np.integer)):  # a symbolic size (jax.export for any batch): no static chunk
        return _everywhere(fn, need, args, fill)
    chunk = chunk_size(n)
    n_slots = -(-n // chunk) * chunk
    # indices of the needing lanes first, padded with n (an index past the end: dropped)
    order = jnp.nonzero(flat_need, size=n_slots, fill_value=n)[0]
    n_chunks = (jnp.sum(flat_need, dtype=jnp.int32) + chunk - 1) // chunk
    lane_shape = jax.eval_shape(fn, *(jax.ShapeDtypeStruct((chunk,), x.dtype) for x in flat_args))
    out = jax.tree.map(lambda s: jnp.full((n,), fill, s.dtype), lane_shape)

    def body(i, out):
        ids = jax.lax.dynamic_slice(order, (i * chunk,), (chunk,))
        lanes = [x.at[ids].get(mode="clip") for x in flat_args]
        result = fn(*lanes)
        return jax.tree.map(lambda o, r: o.at[ids].set(r, mode="drop"), out, result)

    out = jax.lax.fori_loop(0, n_chunks, body, out)
    return jax.tree.map(lambda o: o.reshape(shape), out)
