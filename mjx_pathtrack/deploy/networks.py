"""The networks a policy runs on: the papers' separate policy and value MLPs (Brax PPO networks)
and their settings, :class:`NetworkConfig`. Training (:mod:`mjx_pathtrack.rl.ppo`) builds them to
learn the parameters; evaluation and export rebuild them to run the learned parameters.
"""

from __future__ import annotations

import dataclasses
import functools

import jax
import numpy as np

from mjx_pathtrack.envs.tracking import PathTrackingEnv


@dataclasses.dataclass(frozen=True)
class NetworkConfig:
    """The papers' separate policy and value MLPs (swish) and the policy's Gaussian noise.

    ``init_noise_std``: the std at the start; ``final_noise_std``: None: the log-std is learned
    (Brax); a number: the std is set by a schedule, geometric from ``init_noise_std`` to this value
    at the end of training, so that the sampled policy PPO optimises converges to the
    deterministic one. ``mean_init_scale``: scale of the mean head's initial weights (the initial
    mean action is ~0, the middle of every safe range). ``mean_clip``: bound of the policy mean,
    ``mean_clip * x / (1 + |x|)`` (Brax's ``mean_clip_scale``), like the papers' tanh mean head
    (docs/training.md §1); None: unbounded. ``privileged_critic``: the value network also sees
    what the return depends on but the policy's observation does not show: the steps left in the
    time budget, the path length left, braking (:meth:`PathTrackingEnv.critic_features`; training
    only: the policy and its export are unchanged). The stop reward is multiplied by the steps
    left in the budget, so a critic that sees them learns far cleaner advantages (docs/results.md
    "Learning recipe"; off: the papers' value network). ``noise_scale``: ``"PREFIX=FACTOR"``
    entries: the scheduled std of every action joint whose name starts with ``PREFIX`` is
    multiplied by ``FACTOR`` (the first matching entry counts; e.g. ``("leg_=0.2",)`` explores
    ARMAR-4's legs 5x less than its arms; needs the scheduled std, training only)."""

    policy_layers: tuple[int, ...] = (256, 128)
    value_layers: tuple[int, ...] = (256, 128)
    init_noise_std: float = 0.5
    final_noise_std: float | None = 0.05
    mean_init_scale: float = 0.01
    mean_clip: float | None = None
    privileged_critic: bool = True
    noise_scale: tuple[str, ...] = ()



def parse_noise_scale(entry: str) -> tuple[str, float]:
    """``(prefix, factor)`` of a ``NetworkConfig.noise_scale`` entry ``"PREFIX=FACTOR"``. Raises
    ``ValueError`` naming the entry unless the prefix is non-empty and the factor a finite
    number > 0."""
    prefix, sep, text = str(entry).partition("=")
    try:
        factor = float(text)
    except ValueError:
        factor = float("nan")
    if not sep or not prefix or not (np.isfinite(factor) and factor > 0):
        raise ValueError(f"noise scale {entry!r}: expected PREFIX=FACTOR with a factor > 0 (e.g. leg_=0.2)")
    return prefix, factor


def noise_factors(entries: tuple[str, ...], joint_names) -> np.ndarray:
    """Factors ``[n_actions]`` [-] on the policy's scheduled std, one per action joint of
    ``joint_names`` (in action order), from ``NetworkConfig.noise_scale`` entries
    ``"PREFIX=FACTOR"``: the first entry whose prefix starts the joint's name gives its factor,
    1 where none does. Raises ``ValueError`` naming an entry that is malformed
    (:func:`parse_noise_scale`) or matches no joint."""
    names = list(joint_names)
    factors = np.ones(len(names), np.float32)
    claimed = np.zeros(len(names), bool)
    for entry in entries:
        prefix, factor = parse_noise_scale(entry)
        hits = np.array([n.startswith(prefix) for n in names], bool)
        if not hits.any():
            raise ValueError(f"noise scale {entry!r}: no action joint starts with {prefix!r} "
                             f"(joints: {', '.join(names)})")
        factors[hits & ~claimed] = factor
        claimed |= hits
    return factors


#: number of extra inputs of a privileged value network (``NetworkConfig.privileged_critic``;
#: :meth:`mjx_pathtrack.envs.tracking.PathTrackingEnv.critic_features`)
CRITIC_FEATURES = len(PathTrackingEnv.CRITIC_FEATURES)


def networks(config, prior=None):
    """Brax PPO network factory for ``config`` (a :class:`~mjx_pathtrack.config.run.NetworkConfig`): separate policy and value
    MLPs (``policy_layers``, ``value_layers``, swish), a Gaussian policy whose samples the
    environment clips to [-1, 1], a learned state-independent log-std starting at
    ``init_noise_std``, a mean head initialised near zero (``mean_init_scale``; the initial
    mean action is ~0, the middle of every safe range), optionally bounded (``mean_clip``).

    The factory's ``observation_size`` is the policy's observation. With
    ``config.privileged_critic`` the value network takes :data:`CRITIC_FEATURES` more inputs
    (:class:`~mjx_pathtrack.envs.wrappers.CriticFeatures`), the observation statistics cover all of
    them, and the policy normalises and reads only the first ``observation_size``: the same
    parameters then act on the plain observation (evaluation, export) and on the extended one
    (training).

    ``prior``: an action prior (:mod:`mjx_pathtrack.envs.action_prior`; a function of the
    observation, ``[..., obs] -> [..., n_actions]``, without parameters) added to the policy's
    mean, so that at a zero network output the policy acts as the prior; the deterministic policy
    and its export include it. None: none."""
    factory = _networks(config)
    if prior is None:
        return factory

    def make(observation_size: int, action_size: int, preprocess_observations_fn):
        nets = factory(observation_size, action_size, preprocess_observations_fn=preprocess_observations_fn)
        apply = nets.policy_network.apply

        def apply_with_prior(processor_params, policy_params, obs):
            mean, std = apply(processor_params, policy_params, obs)
            return mean + prior(obs).astype(mean.dtype), std

        policy = dataclasses.replace(nets.policy_network, apply=apply_with_prior)
        return nets.replace(policy_network=policy)

    return make


def policy_network_factory(config):
    """The network factory of a training run's policy, the one place it is built (training,
    evaluation, export, warm starts, sweeps): :func:`networks` of ``config.network`` with the
    run's action prior (``--leg-prior``; :func:`~mjx_pathtrack.envs.tasks.humanoid_balance.action_prior`).
    ``config``: a :class:`~mjx_pathtrack.config.run.TrainConfig` (or any config with a
    ``network`` block; one without a ``task`` has no prior)."""
    from mjx_pathtrack.envs.tasks import humanoid_balance

    return networks(config.network, humanoid_balance.action_prior(config))


def policy_networks(config, observation_size: int, action_size: int):
    """Brax PPO networks of a training run's policy (:func:`policy_network_factory`) for an
    environment's ``observation_size`` and ``action_size``, observations normalised by Brax's
    running statistics, as training builds them."""
    from brax.training.acme import running_statistics

    return policy_network_factory(config)(int(observation_size), int(action_size),
                                          preprocess_observations_fn=running_statistics.normalize)


def params_observation_size(params) -> int:
    """The observation size ``[obs]`` that trained parameters ``(normaliser, policy, value)``
    read: the inputs of the policy network's first layer (the value network and the normaliser
    may see more: ``privileged_critic``). Raises ``ValueError`` if ``params`` do not hold a
    policy network of :func:`networks`."""
    try:
        return int(params[1]["params"]["MLP_0"]["hidden_0"]["kernel"].shape[0])
    except (TypeError, KeyError, IndexError, AttributeError) as e:
        raise ValueError(f"not the parameters of a policy network (no policy first layer: {type(e).__name__}: {e})") from e


def _networks(config):
    """:func:`networks` without a prior."""
    from brax.training import networks as brax_nets
    from brax.training.agents.ppo import networks as brax_networks

    layers = dict(policy_hidden_layer_sizes=config.policy_layers, value_hidden_layer_sizes=config.value_layers,
                  distribution_type="normal", noise_std_type="log", init_noise_std=config.init_noise_std,
                  mean_clip_scale=config.mean_clip, mean_kernel_init_fn=jax.nn.initializers.variance_scaling,
                  mean_kernel_init_kwargs=dict(scale=config.mean_init_scale ** 2, mode="fan_in",
                                               distribution="truncated_normal"))
    if not config.privileged_critic:
        return functools.partial(brax_networks.make_ppo_networks, **layers)

    def make(observation_size: int, action_size: int, preprocess_observations_fn):
        size = int(observation_size)

        def policy_preprocess(obs, stats):  # the running statistics of the first ``size`` inputs
            return (obs[..., :size] - stats.mean[:size]) / stats.std[:size]

        policy = brax_networks.make_ppo_networks(size, action_size, policy_preprocess, **layers)
        value = brax_nets.make_value_network(size + CRITIC_FEATURES, preprocess_observations_fn,
                                             hidden_layer_sizes=config.value_layers, activation=jax.nn.swish)
        return brax_networks.PPONetworks(policy_network=policy.policy_network, value_network=value,
                                         parametric_action_distribution=policy.parametric_action_distribution)

    return make
