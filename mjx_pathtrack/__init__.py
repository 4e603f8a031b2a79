"""mjx_pathtrack: time-optimized, jerk-limited robot path tracking learned with MJX, JAX and Brax PPO.

Importing the package has no side effects. A program that steps batched MJX physics on a CPU
calls :func:`prepare_xla` before JAX starts (the package's entry points do): XLA's default CPU
fusion emitters make it ~1000x slower (mjx_pathtrack/_xla.py).
"""

from mjx_pathtrack._xla import configure_xla_flags
from mjx_pathtrack._xla import prepare as prepare_xla

__version__ = "0.1.0"

__all__ = ["__version__", "configure_xla_flags", "prepare_xla"]
