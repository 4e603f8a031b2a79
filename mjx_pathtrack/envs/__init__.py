"""Environments: the batched path-tracking environment, its executors, wrappers and task variants.

- :mod:`~mjx_pathtrack.envs.tracking`: ``PathTrackingEnv`` and ``EnvConfig`` (one decision step);
- :mod:`~mjx_pathtrack.envs.episodes`: the rollout engine (a policy scanned over batched episodes);
- :mod:`~mjx_pathtrack.envs.executors`: kinematic and MJX executors of a decision step;
- :mod:`~mjx_pathtrack.envs.wrappers`: Brax training wrappers;
- :mod:`~mjx_pathtrack.envs.action_prior`: actions a policy's mean is added to (the hold of ARMAR-4's legs);
- :mod:`~mjx_pathtrack.envs.tasks`: ball on plate, humanoid balance, velocity maximisation.
"""
