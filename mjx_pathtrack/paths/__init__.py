"""Reference paths: the on-disk datasets, their generators (one module per kind), import and IK.

- :mod:`~mjx_pathtrack.paths.datasets`: the dataset format, loading, statistics, validation, import;
- :mod:`~mjx_pathtrack.paths.generate`: the generator registry (``KINDS``) and random paths;
- :mod:`~mjx_pathtrack.paths.target`, :mod:`~mjx_pathtrack.paths.ball`: target-point and ball paths;
- :mod:`~mjx_pathtrack.paths.ik`: inverse kinematics for Cartesian paths;
- :mod:`~mjx_pathtrack.paths.user_paths`: a user's path made ready for a policy (limits, re-knotting);
- :mod:`~mjx_pathtrack.paths.families`: path families of the generalisation benchmark;
- :mod:`~mjx_pathtrack.paths.train_data`: regenerating a larger train split for a run;
- ``python -m mjx_pathtrack.paths {generate,stats,import}``: the command line (:mod:`~mjx_pathtrack.paths.cli`).
"""
