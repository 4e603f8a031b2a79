"""Import ``mujoco.mjx`` once with its optional-backend notices silenced.

``mujoco.mjx`` (imported by Brax too) prints "Failed to import warp: ..." and "Failed to import
mujoco_warp: ..." on stdout when the optional NVIDIA Warp backend is not installed, which this
project never uses. Importing this module first imports ``mujoco.mjx`` with exactly those lines
dropped (anything else it prints is passed on); later imports are then silent.
"""

from __future__ import annotations

import contextlib
import io
import sys

_NOTICES = ("Failed to import warp", "Failed to import mujoco_warp")


def import_mjx_quietly() -> None:
    if "mujoco.mjx" in sys.modules:
        return
    captured = io.StringIO()
    with contextlib.redirect_stdout(captured):
        import mujoco.mjx  # noqa: F401
    rest = [line for line in captured.getvalue().splitlines() if not line.startswith(_NOTICES)]
    if rest:
        print("\n".join(rest))


import_mjx_quietly()
