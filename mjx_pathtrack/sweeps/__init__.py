"""Trade-off sweeps: a grid of training runs from one YAML file and their analysis.

- :mod:`~mjx_pathtrack.sweeps.spec`: the sweep file, its grid points, validation;
- :mod:`~mjx_pathtrack.sweeps.run`: training and evaluating the points (batched where possible);
- :mod:`~mjx_pathtrack.sweeps.analysis`: tables, Pareto fronts and the paper's rows (the notebook's logic).
"""
