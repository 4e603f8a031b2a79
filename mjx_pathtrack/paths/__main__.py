"""``python -m mjx_pathtrack.paths``: see :mod:`mjx_pathtrack.paths.cli`."""

import sys

import mjx_pathtrack

# before JAX starts: generation and import run MJX kinematics (IK, FK, self-collision), which
# XLA's default CPU emitters make ~100x slower (a target-point split took hours instead of minutes)
mjx_pathtrack.prepare_xla()

from mjx_pathtrack.paths.cli import main  # noqa: E402

sys.exit(main())
