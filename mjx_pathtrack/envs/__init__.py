"""Environments: the batched path-tracking environment, its executors, wrappers and task variants.

- :mod:`~mjx_pathtrack.envs.tracking`: ``PathTrackingEnv`` and ``EnvConfig`` (one decision step);
- :mod:`~mjx_pathtrack.envs.episodes`: the rollout engine (a policy scanned over batched episodes);
- :mod:`~mjx_pathtrack.envs.executors`: kinematic and MJX executors of a decision step;
- :mod:`~mjx_pathtrack.envs.wrappers`: Brax training wrappers;
- :mod:`~mjx_pathtrack.envs.tasks`: ball on plate, humanoid balance, velocity maximisation.
"""
