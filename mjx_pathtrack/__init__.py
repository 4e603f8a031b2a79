"""mjx_pathtrack: time-optimized, jerk-limited robot path tracking learned with MJX, JAX and Brax PPO."""

import os as _os
import warnings as _warnings

from mjx_pathtrack._xla import FUSION_FLAG, OPT_OUT_VAR, configure_xla_flags, jax_backend_initialized

__version__ = "0.1.0"

# Must run before anything in this package imports jax (see mjx_pathtrack/_xla.py).
if configure_xla_flags(_os.environ) and jax_backend_initialized():
    _warnings.warn(
        f"mjx_pathtrack: JAX's backend was initialised before mjx_pathtrack was imported, so "
        f"XLA_FLAGS {FUSION_FLAG} could not take effect and batched MJX on CPU may be ~1000x "
        f"slower. Import mjx_pathtrack before using jax, or set XLA_FLAGS='{FUSION_FLAG}' in "
        f"the environment before starting Python (set {OPT_OUT_VAR}=1 to silence this).",
        RuntimeWarning,
        stacklevel=2,
    )

__all__ = ["__version__", "configure_xla_flags"]
