"""XLA flag set-up that must run before JAX creates its CPU backend.

Why: with jax >= 0.9 the XLA CPU backend's new "fusion emitters" make batched
(``vmap``-ed) ``mjx.step`` roughly 1000x slower than with the flag
``--xla_cpu_use_fusion_emitters=false`` (measured on this project's arm
environments). XLA reads ``XLA_FLAGS`` once, when the first backend is
initialised, so the flag has to be in the environment before then. Importing the package
changes nothing; its entry points (``train.py``, ``evaluate.py``, the benchmarks and scripts)
call :func:`prepare` first, and so should a user's own program that runs batched MJX on a CPU
(``mjx_pathtrack.prepare_xla()``; :class:`~mjx_pathtrack.envs.executors.MjxExecutor` warns when the
flag is missing).

The flag only affects the CPU backend, so setting it on a GPU/TPU run is
harmless; the platform check below errs towards setting it.

XLA aborts the whole process on an unknown flag in XLA_FLAGS, and the flag is gone
from jaxlib 0.11 (measured: jaxlib 0.11.2 aborts with "Unknown flag in XLA_FLAGS:
--xla_cpu_use_fusion_emitters=false"). The flag is therefore only added for jaxlib
versions below ``FLAG_REMOVED_IN`` (read from the installed distribution's metadata,
without importing jaxlib). The project pins jax 0.9.2, where it exists and matters.

Opt out with ``MJX_PATHTRACK_NO_XLA_FLAGS=1``.

The flag only pays off for MJX physics. Everything else (the kinematic executor's environment
step together with Brax's PPO updates, whose elementwise and reduction fusions the old emitters
compile worse) trains faster with XLA's default emitters: measured 34,277 against 30,095 PPO
env-steps/s at 2048 iiwa environments (``benchmarks/bench_train.py``, docs/results.md "CPU XLA flags"). A process that
knows before JAX starts that it will run no MJX physics (``train.py`` with the kinematic
executor) calls ``prepare(mjx_physics=False)``, which takes out a flag this package added
in a parent process (:func:`drop_cpu_fix`; marked in ``MJX_PATHTRACK_ADDED_XLA_FLAG``, so a
child process can tell it from a user's).

This module must not import jax.
"""

from __future__ import annotations

import os
import re
import sys
import warnings
from collections.abc import Mapping, MutableMapping

FUSION_FLAG_NAME = "xla_cpu_use_fusion_emitters"
FUSION_FLAG = f"--{FUSION_FLAG_NAME}=false"
OPT_OUT_VAR = "MJX_PATHTRACK_NO_XLA_FLAGS"
#: holds FUSION_FLAG while the flag in XLA_FLAGS is the one this package added (not the user's)
ADDED_VAR = "MJX_PATHTRACK_ADDED_XLA_FLAG"
FLAG_REMOVED_IN = (0, 11)  # first jaxlib (major, minor) whose XLA rejects the flag

_FALSY = {"", "0", "false", "no", "off"}


def _opted_out(environ: Mapping[str, str]) -> bool:
    return environ.get(OPT_OUT_VAR, "").strip().lower() not in _FALSY


def _may_run_on_cpu(environ: Mapping[str, str]) -> bool:
    """True unless JAX_PLATFORMS (or, if unset, JAX_PLATFORM_NAME) names only non-cpu platforms."""
    spec = environ.get("JAX_PLATFORMS", "").strip() or environ.get("JAX_PLATFORM_NAME", "").strip()
    names = [name.strip().lower() for name in spec.split(",") if name.strip()]
    return not names or "cpu" in names


def _has_fusion_flag(xla_flags: str) -> bool:
    """True if the user already set the fusion-emitter flag, to any value."""
    for token in xla_flags.split():
        name = token.lstrip("-").split("=", 1)[0]
        if name in (FUSION_FLAG_NAME, "no" + FUSION_FLAG_NAME):
            return True
    return False


def installed_jaxlib_version() -> str | None:
    """The installed jaxlib's version string from package metadata (no import), or None."""
    from importlib import metadata

    try:
        return metadata.version("jaxlib")
    except metadata.PackageNotFoundError:
        return None


def jaxlib_knows_flag(version: str | None) -> bool:
    """True if XLA in jaxlib ``version`` accepts the fusion-emitter flag.

    Unknown or unparsable versions count as knowing it (the pinned jaxlib does).
    """
    if version is None:
        return True
    parts = re.match(r"(\d+)\.(\d+)", version)
    if parts is None:
        return True
    return (int(parts.group(1)), int(parts.group(2))) < FLAG_REMOVED_IN


def xla_flags_with_cpu_fix(
    environ: Mapping[str, str], jaxlib_version: str | None = None
) -> str | None:
    """The XLA_FLAGS value this package wants, or None to leave XLA_FLAGS alone.

    Pure: reads ``environ`` and ``jaxlib_version`` only. Returns None when opted out, when
    the run will not use the CPU backend, when the user already chose a value for the
    fusion-emitter flag, or when that jaxlib's XLA no longer has the flag. Otherwise returns
    the user's flags (kept verbatim) with ``FUSION_FLAG`` appended.
    """
    current = environ.get("XLA_FLAGS", "")
    if _opted_out(environ) or not _may_run_on_cpu(environ) or _has_fusion_flag(current):
        return None
    if not jaxlib_knows_flag(jaxlib_version):
        return None
    return f"{current} {FUSION_FLAG}".strip()


def configure_xla_flags(environ: MutableMapping[str, str] = os.environ) -> bool:
    """Append ``--xla_cpu_use_fusion_emitters=false`` to ``environ["XLA_FLAGS"]`` if wanted.

    Never replaces or duplicates the user's flags and respects an explicit user value of
    the flag and the ``MJX_PATHTRACK_NO_XLA_FLAGS=1`` opt-out (see
    :func:`xla_flags_with_cpu_fix`). Touches nothing but ``environ``.

    Returns True if ``environ`` was changed.
    """
    new_flags = xla_flags_with_cpu_fix(environ, installed_jaxlib_version())
    if new_flags is None:
        return False
    environ["XLA_FLAGS"] = new_flags
    environ[ADDED_VAR] = FUSION_FLAG
    return True


def drop_cpu_fix(environ: MutableMapping[str, str] = os.environ) -> bool:
    """Take out the fusion-emitter flag again if this package added it, for a process that will
    run no MJX physics (XLA's default emitters are faster there; module docstring).

    Only a flag marked in ``ADDED_VAR`` is removed (never a user's), and in this process's own
    environment only while JAX's backend has not read XLA_FLAGS yet (else nothing changes).
    Returns True if ``environ`` was changed.
    """
    tokens = environ.get("XLA_FLAGS", "").split()
    if environ.get(ADDED_VAR) != FUSION_FLAG or FUSION_FLAG not in tokens:
        return False
    if environ is os.environ and jax_backend_initialized():
        return False
    del tokens[len(tokens) - 1 - tokens[::-1].index(FUSION_FLAG)]  # the last one: the one appended
    if tokens:
        environ["XLA_FLAGS"] = " ".join(tokens)
    else:
        del environ["XLA_FLAGS"]
    del environ[ADDED_VAR]
    return True


def prepare(mjx_physics: bool = True, environ: MutableMapping[str, str] = os.environ) -> bool:
    """Set up XLA_FLAGS for this process before JAX starts (the first call of an entry point).

    ``mjx_physics``: the process will step batched MJX physics on the CPU, so the
    fusion-emitter flag is appended (:func:`configure_xla_flags`); False: a flag this package
    added in a parent process is taken out again (:func:`drop_cpu_fix`). A user's own flags
    are kept either way. Warns (``RuntimeWarning``) if the flag was wanted but JAX's backend had
    already read XLA_FLAGS. Returns True if ``environ`` was changed."""
    if not mjx_physics:
        return drop_cpu_fix(environ)
    changed = configure_xla_flags(environ)
    if changed and environ is os.environ and jax_backend_initialized():
        warnings.warn(
            f"mjx_pathtrack: JAX's backend was initialised before mjx_pathtrack.prepare_xla(), so XLA_FLAGS "
            f"{FUSION_FLAG} could not take effect and batched MJX on CPU may be ~1000x slower. Call it before "
            f"using jax, or set XLA_FLAGS='{FUSION_FLAG}' in the environment before starting Python "
            f"(set {OPT_OUT_VAR}=1 to silence this).", RuntimeWarning, stacklevel=2)
    return changed


def flag_missing(environ: Mapping[str, str] = os.environ) -> bool:
    """True if batched MJX on the CPU would run without the fusion-emitter flag although this
    jaxlib has it and the user did not opt out or choose a value."""
    return xla_flags_with_cpu_fix(environ, installed_jaxlib_version()) is not None


def jax_backend_initialized() -> bool:
    """True if jax is imported and has (or may have) already read XLA_FLAGS.

    XLA parses XLA_FLAGS when the first backend is created (e.g. on ``jax.devices()``),
    not on ``import jax``, so an imported but unused jax still picks the flag up.
    """
    if "jax" not in sys.modules:
        return False
    try:
        from jax._src import xla_bridge

        return bool(xla_bridge.backends_are_initialized())
    except Exception:  # private API moved: assume the worst
        return True
