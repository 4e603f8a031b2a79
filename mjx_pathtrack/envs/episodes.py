"""The rollout engine: a policy scanned over a batch of episodes, without auto-reset, jitted.

Every rollout of the package goes through :func:`run_episodes`: the evaluation of the
path-tracking environment (:mod:`mjx_pathtrack.evaluation.rollout`, which the sweeps use too)
and the velocity task's (:mod:`mjx_pathtrack.envs.tasks.velocity_max`). The engine owns the loop
and the episode bookkeeping; the caller says what to accumulate and what to record:

- ``accumulate(acc, before, after, live, steps) -> acc``: folds one step into the caller's
  running values (``before``/``after``: the env states around the step, ``live`` ``[B...]``
  bool: the step belongs to the episode, ``steps`` ``[B...]``: live steps before this one);
- ``record(before, after, live) -> pytree``: what to keep of every step, returned time-major
  ``[T, B..., ...]`` (``None``: nothing).

An episode ends at the first step whose ``after.done`` is set; from then on its state is frozen
(the env is still stepped, batched, but its result is discarded), ``live`` is false and
``steps`` stops counting. ``B...`` is any batch shape that ``step`` accepts.
"""

from __future__ import annotations

from typing import Any, Callable, NamedTuple

import jax
import jax.numpy as jnp

Array = jax.Array
#: ``policy(obs [B..., obs_size], key) -> action [B..., n]``
Policy = Callable[[Array, Array], Array]


class EpisodeLoop(NamedTuple):
    """The scan's carry: env states ``[B...]``, ``done`` ``[B...]`` bool (episode over, state
    frozen), ``steps`` ``[B...]`` float (live steps so far) and the caller's accumulator."""

    state: Any
    done: Array
    steps: Array
    acc: Any


def run_episodes(step: Callable[[Any, Array], Any], policy: Policy, state, keys: Array,
                 accumulate: Callable[..., Any], acc, record: Callable[..., Any] | None = None
                 ) -> tuple[EpisodeLoop, Any]:
    """Scan ``policy`` and the batched ``step(state, action) -> state`` over ``len(keys)`` steps
    from the batch ``state`` (a Brax-style state with ``obs`` and ``done``); ``keys`` ``[T, 2]``
    are the policy's per-step keys. Returns the final :class:`EpisodeLoop` and the time-major
    records (``None`` without ``record``). See the module docstring for ``accumulate``/``record``."""
    batch = state.done.shape

    def body(loop: EpisodeLoop, key):
        action = policy(loop.state.obs, key)
        nxt = step(loop.state, action)
        live = ~loop.done
        acc = accumulate(loop.acc, loop.state, nxt, live, loop.steps)
        out = record(loop.state, nxt, live) if record is not None else None
        keep = jax.tree.map(lambda a, b: jnp.where(live.reshape(live.shape + (1,) * (a.ndim - live.ndim)), a, b),
                            nxt, loop.state)
        return EpisodeLoop(keep, loop.done | (live & (nxt.done > 0)), loop.steps + live, acc), out

    init = EpisodeLoop(state, jnp.zeros(batch, bool), jnp.zeros(batch), acc)
    return jax.lax.scan(body, init, keys)
