"""Brax training wrappers: batch, episode bookkeeping, and auto-reset with *fresh* episodes.

Brax's own ``AutoResetWrapper`` restores the state an environment had after its first reset,
so every environment slot would replay the same path forever. :class:`FreshAutoResetWrapper`
instead draws a new episode (new path, new sub-path) from a key carried in the environment's
state whenever an episode ends. Pass :func:`wrap_for_training` as ``wrap_env_fn`` to
``brax.training.agents.ppo.train``.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
from mjx_pathtrack import _quiet  # noqa: F401,I001  (before brax / mujoco.mjx: silences their Warp notices)
from brax.envs.base import Env, State, Wrapper
from brax.envs.wrappers.training import EpisodeWrapper, VmapWrapper


class FreshAutoResetWrapper(Wrapper):
    """Resets finished environments (batched) to newly drawn episodes.

    The wrapped (vmapped) environment's ``pipeline_state`` must have a field ``rng`` (a key per
    environment); reset keys are split from it, so runs are reproducible for a seed.
    """

    def reset(self, rng: jax.Array) -> State:
        return self.env.reset(rng)

    def step(self, state: State, action: jax.Array) -> State:
        if "steps" in state.info:
            state.info.update(steps=jnp.where(state.done, jnp.zeros_like(state.info["steps"]), state.info["steps"]))
        state = state.replace(done=jnp.zeros_like(state.done))
        state = self.env.step(state, action)
        keys = jax.vmap(jax.random.split)(state.pipeline_state.rng)
        fresh = self.env.reset(keys[:, 0])
        done = state.done.astype(bool)

        def pick(new, old):
            return jnp.where(done.reshape(done.shape + (1,) * (old.ndim - 1)), new, old)

        pipeline_state = jax.tree.map(pick, fresh.pipeline_state, state.pipeline_state)
        pipeline_state = pipeline_state._replace(rng=jnp.where(done[:, None], pipeline_state.rng, keys[:, 1]))
        return state.replace(pipeline_state=pipeline_state, obs=pick(fresh.obs, state.obs))


class CriticFeatures(Wrapper):
    """Appends :meth:`~mjx_pathtrack.envs.tracking.PathTrackingEnv.critic_features` to the observation
    (unbatched environment, innermost wrapper): ``[obs_size + 3]``. For training with a value
    network that sees them (:func:`mjx_pathtrack.rl.ppo.networks`); the policy reads only the
    first ``obs_size`` entries, so evaluation, export and deployment see the plain observation."""

    @property
    def observation_size(self) -> int:
        return self.env.observation_size + len(self.env.CRITIC_FEATURES)

    def _extend(self, state: State) -> State:
        return state.replace(obs=jnp.concatenate([state.obs, self.env.critic_features(state.pipeline_state)]))

    def reset(self, rng: jax.Array) -> State:
        return self._extend(self.env.reset(rng))

    def step(self, state: State, action: jax.Array) -> State:
        return self._extend(self.env.step(state, action))


def wrap_for_training(env: Env, episode_length: int = 1000, action_repeat: int = 1,
                      randomization_fn=None) -> Env:
    """``VmapWrapper`` + ``EpisodeWrapper`` + :class:`FreshAutoResetWrapper` (the signature of
    Brax's ``wrap_env_fn``; domain randomisation is not supported here and raises)."""
    if randomization_fn is not None:
        raise ValueError("wrap_for_training does not support randomization_fn")
    return FreshAutoResetWrapper(EpisodeWrapper(VmapWrapper(env), episode_length, action_repeat))
