"""Reinforcement learning: the PPO learner and the training loop (the configuration of a run, its
directory and checkpoints are :mod:`mjx_pathtrack.config`).

- :mod:`~mjx_pathtrack.rl.training`: ``train`` (run directory, progress, evaluation, export);
- :mod:`~mjx_pathtrack.rl.warm_start`: ``--init-from``, a finished run's networks matched to another run by name;
- :mod:`~mjx_pathtrack.rl.ppo`: Brax PPO as a pure function of the learner state;
- :mod:`~mjx_pathtrack.rl.batched_ppo`: several PPO learners trained as one batched program (sweeps);
- :mod:`~mjx_pathtrack.rl.velocity_max_train`: training and the optimum of the velocity task (paper 001).
"""
