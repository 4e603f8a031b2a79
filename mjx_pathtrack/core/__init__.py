"""The pure math of path tracking: JAX functions, jittable and vmappable, no robot or simulator.

- :mod:`~mjx_pathtrack.core.limits`: joint limits and the safe acceleration range (paper 001);
- :mod:`~mjx_pathtrack.core.stopping`: the braking models the safe range is built from;
- :mod:`~mjx_pathtrack.core.spline`: the reference path as a batched, arc-length-parameterised spline;
- :mod:`~mjx_pathtrack.core.spline_fit`: fitting and resampling a spline through knots (NumPy);
- :mod:`~mjx_pathtrack.core.knot_rule`: the training data's knot rule applied to any curve (NumPy);
- :mod:`~mjx_pathtrack.core.reward`: the reward terms of paper 000;
- :mod:`~mjx_pathtrack.core.compaction`: action compaction of the safe range's output.
"""
