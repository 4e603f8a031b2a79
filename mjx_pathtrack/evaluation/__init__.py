"""Evaluation: rollouts of a policy, the run report, plots and the time-optimal baselines.

- :mod:`~mjx_pathtrack.evaluation.rollout`: batched evaluation episodes and their summary;
- :mod:`~mjx_pathtrack.evaluation.report`: ``evaluate.py``'s report of a run or an export;
- :mod:`~mjx_pathtrack.evaluation.baseline`: TOPP-RA durations (toppra);
- :mod:`~mjx_pathtrack.evaluation.jerk_optimum`: the jerk-limited optimum (copp-py's TOPP3);
- :mod:`~mjx_pathtrack.evaluation.plots`, :mod:`~mjx_pathtrack.evaluation.limits_demo`: figures.
"""
