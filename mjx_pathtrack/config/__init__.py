"""The configuration of a run, below the code that trains, evaluates and sweeps it:
:mod:`~mjx_pathtrack.config.run` (``TrainConfig`` nested by concern, flat option names,
validation), :mod:`~mjx_pathtrack.config.options` (nested configs with flat names, JSON,
command-line flags), :mod:`~mjx_pathtrack.config.presets` (robot presets, ``--preset`` recipes),
:mod:`~mjx_pathtrack.config.run_dir` (the run directory and exact checkpoints, for ``--resume``),
:mod:`~mjx_pathtrack.config.stored` (parameters and checkpoints as data: loading runs no code)."""
