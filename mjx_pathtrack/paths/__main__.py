"""``python -m mjx_pathtrack.paths``: see :mod:`mjx_pathtrack.paths.cli`."""

import sys

from mjx_pathtrack.paths.cli import main

sys.exit(main())
