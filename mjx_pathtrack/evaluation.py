"""Episode metrics of a policy on a path-tracking environment (paper 000 Table I fields).

:func:`evaluate` runs a batch of episodes to their end (no auto-reset), jitted and vmapped, and
returns per-episode arrays; :func:`summarize` turns them into the numbers the README reports.
"""

from __future__ import annotations

from typing import Any, Callable, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from mjx_pathtrack.env import PathTrackingEnv

Array = jax.Array
#: ``policy(obs [B, obs_size], key) -> action [B, n]``
Policy = Callable[[Array, Array], Array]


class EpisodeMetrics(NamedTuple):
    """Per-episode results ``[B]``: return; steps until done; time [s] when the path end was
    first reached and when the robot had stopped (``nan`` if never); mean over steps of d_mean
    and max of d_max [rad]; success (stopped / timed out with the last point within the success
    deviation of the end knot); terminated on deviation; final arc progress in [0, 1]."""

    episode_return: Array
    steps: Array
    end_time: Array
    stop_time: Array
    mean_deviation: Array
    max_deviation: Array
    success: Array
    terminated_deviation: Array
    progress: Array


def evaluate(env: PathTrackingEnv, policy: Policy, rng: Array, n_episodes: int,
             max_steps: int | None = None) -> EpisodeMetrics:
    """Run ``n_episodes`` episodes (reset keys split from ``rng``) until done or ``max_steps``
    (default: the config's longest episode); metrics after ``done`` are frozen."""
    dt = env.config.dt
    max_steps = env.config.max_episode_steps() + 1 if max_steps is None else max_steps
    reset_keys = jax.random.split(rng, n_episodes + 1)
    state = jax.vmap(env.reset)(reset_keys[1:])
    zeros = jnp.zeros(n_episodes)
    nan = jnp.full(n_episodes, jnp.nan)
    init = (state, jnp.zeros(n_episodes, bool), zeros, zeros, nan, nan, zeros, zeros, zeros, zeros, zeros)

    def body(carry, key):
        state, done, ret, steps, end_t, stop_t, dsum, dmax, success, term_dev, progress = carry
        action = policy(state.obs, key)
        nxt = jax.vmap(env.step)(state, action)
        live = ~done
        m = nxt.metrics
        t = (steps + 1) * dt
        reached = live & (m["reached_end"] > 0)
        end_t = jnp.where(reached & jnp.isnan(end_t), t, end_t)
        now_done = live & (nxt.done > 0)
        stopped = now_done & (m["reached_end"] > 0) & (m["terminated_deviation"] == 0)
        stop_t = jnp.where(stopped & jnp.isnan(stop_t), t, stop_t)
        carry = (jax.tree.map(lambda a, b: jnp.where(live.reshape(live.shape + (1,) * (a.ndim - 1)), a, b), nxt, state),
                 done | now_done,
                 ret + jnp.where(live, nxt.reward, 0.0),
                 steps + live,
                 end_t, stop_t,
                 dsum + jnp.where(live, m["d_mean"], 0.0),
                 jnp.where(live, jnp.maximum(dmax, m["d_max"]), dmax),
                 jnp.where(now_done, m["success"], success),
                 jnp.where(now_done, m["terminated_deviation"], term_dev),
                 jnp.where(live, m["progress"], progress))
        return carry, None

    final, _ = jax.lax.scan(body, init, jax.random.split(reset_keys[0], max_steps))
    _, _, ret, steps, end_t, stop_t, dsum, dmax, success, term_dev, progress = final
    return EpisodeMetrics(ret, steps, end_t, stop_t, dsum / jnp.maximum(steps, 1), dmax, success, term_dev, progress)


def summarize(m: EpisodeMetrics) -> dict[str, float]:
    """Means over episodes: return, end-reached rate, success rate, mean stop time [s] (of the
    episodes that stopped), mean/max joint deviation [rad], deviation terminations."""
    m = jax.tree.map(np.asarray, m)
    stopped = ~np.isnan(m.stop_time)
    return {
        "return": float(m.episode_return.mean()),
        "end_reached": float((~np.isnan(m.end_time)).mean()),
        "success": float(m.success.mean()),
        "stop_time_s": float(m.stop_time[stopped].mean()) if stopped.any() else float("nan"),
        "mean_deviation": float(m.mean_deviation.mean()),
        "max_deviation": float(m.max_deviation.mean()),
        "terminated_deviation": float(m.terminated_deviation.mean()),
        "progress": float(m.progress.mean()),
    }


def brax_policy(make_inference_fn, params, deterministic: bool = True) -> Policy:
    """A :data:`Policy` from Brax PPO's ``make_inference_fn`` and trained ``params``."""
    inference = make_inference_fn(params, deterministic=deterministic)
    return lambda obs, key: inference(obs, key)[0]


def make_evaluator(env: PathTrackingEnv, make_inference_fn, n_episodes: int, max_steps: int | None = None,
                   deterministic: bool = True) -> Callable[[Any, Array], EpisodeMetrics]:
    """``evaluator(params, rng) -> EpisodeMetrics``, jitted once (params are an argument, so
    evaluating new parameters during training does not recompile)."""

    @jax.jit
    def evaluator(params, rng):
        return evaluate(env, brax_policy(make_inference_fn, params, deterministic), rng, n_episodes, max_steps)

    return evaluator
