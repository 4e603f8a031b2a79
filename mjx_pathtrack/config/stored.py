"""Parameters and checkpoints stored as data: loading a run directory never runs code from it.

A finished run's parameters (``params.msgpack``) and its checkpoints (``checkpoints/*.ckpt``)
are MessagePack files (:mod:`flax.serialization`): nested maps of numbers, strings and arrays
(dtype name, shape and raw bytes), nothing that names a Python object. Reading one builds the
parameter containers this package knows (Brax's observation normaliser, Flax parameter dicts,
the learner of a checkpoint from a freshly built template) and fills them with the stored arrays,
checking every name and shape. Python pickles, which this package wrote before, can carry code
that runs when they are opened: a run directory that has only ``params.pkl`` or pickled
checkpoints is refused with :class:`PickleRefused`, unless the caller opts in
(``--allow-pickle``: only for files you made yourself or trust); ``scripts/convert_run.py``
rewrites such a run as data once.

Parameters ``(normalizer, policy, value)``: ``normalizer`` a Brax ``RunningStatisticsState`` of
observations ``[obs]``; ``policy`` / ``value`` Flax parameter dicts (``{"params": {...}}``).
"""

from __future__ import annotations

import pickle
from pathlib import Path as FsPath
from typing import Any

import numpy as np

#: a finished run's parameters (data only)
PARAMS_FILE = "params.msgpack"
#: the pickled parameters of runs written before (loaded only with ``allow_pickle``)
LEGACY_PARAMS_FILE = "params.pkl"
PARAMS_FORMAT = "mjx_pathtrack.params/1"
CHECKPOINT_FORMAT = "mjx_pathtrack.checkpoint/2"
#: the first bytes of a pickle (protocol 2 and later)
PICKLE_MAGIC = b"\x80"

ALLOW_PICKLE_HELP = ("also load Python pickles (params.pkl, checkpoints of older runs): unpickling runs any code "
                     "the file carries, so only for files you made yourself or trust")


class StoredDataError(ValueError):
    """A parameter or checkpoint file that is not what this package writes (corrupt, another
    format, names or shapes that do not fit)."""


class PickleRefused(StoredDataError):
    """A Python pickle that was not opted into (``allow_pickle``)."""


def _refuse_pickle(path: FsPath) -> PickleRefused:
    return PickleRefused(
        f"{path} is a Python pickle, and opening a pickle runs whatever code it carries: not loaded. If you made "
        f"this run or trust where it came from, pass --allow-pickle, or convert it to data once with "
        f"`python scripts/convert_run.py {path.parent if path.name == LEGACY_PARAMS_FILE else path.parent.parent}`")


def _unpickle(path: FsPath, allow_pickle: bool) -> Any:
    if not allow_pickle:
        raise _refuse_pickle(path)
    try:
        return pickle.loads(path.read_bytes())
    except Exception as e:  # unpickling errors come in many types
        raise StoredDataError(f"corrupt pickle {path}: {type(e).__name__}: {e}") from e


def _restore(path: FsPath) -> dict:
    from flax import serialization

    data = path.read_bytes()
    try:
        restored = serialization.msgpack_restore(data)
    except Exception as e:  # msgpack raises several types; nothing in it can run code
        raise StoredDataError(f"corrupt file {path}: {type(e).__name__}: {e}") from e
    if not isinstance(restored, dict):
        raise StoredDataError(f"{path}: not a file of this package (a {type(restored).__name__} at the top)")
    return _writable(restored)


def _writable(tree: Any) -> Any:
    """The restored arrays as writable copies (MessagePack gives read-only views of its buffer)."""
    if isinstance(tree, dict):
        return {k: _writable(v) for k, v in tree.items()}
    if isinstance(tree, list):
        return [_writable(v) for v in tree]
    return np.array(tree) if isinstance(tree, np.ndarray) else tree


def _fill(template: Any, state: Any, where: str) -> Any:
    """``template`` with its arrays replaced by those of ``state`` (a restored state dict), every
    leaf's shape checked."""
    import jax
    from flax import serialization

    try:
        filled = serialization.from_state_dict(template, state)
    except (KeyError, ValueError, TypeError) as e:
        raise StoredDataError(f"{where}: the stored names do not fit this package's ({e})") from e
    mine, theirs = jax.tree.leaves(template), jax.tree.leaves(filled)
    if len(mine) != len(theirs):
        raise StoredDataError(f"{where}: {len(theirs)} stored arrays where {len(mine)} are expected")
    for a, b in zip(mine, theirs):
        if np.shape(a) != np.shape(b):
            raise StoredDataError(f"{where}: an array of shape {np.shape(b)} where {np.shape(a)} is expected")
    return filled


def _plain(tree: Any, where: str) -> Any:
    """A Flax parameter dict of the restored data: nested string-keyed dicts of float arrays."""
    if isinstance(tree, dict):
        return {str(k): _plain(v, f"{where}/{k}") for k, v in tree.items()}
    if isinstance(tree, np.ndarray) and tree.dtype.kind == "f":
        return tree
    raise StoredDataError(f"{where}: a {type(tree).__name__} where parameters are float arrays")


def normalizer_template(obs_size: int):
    """An empty Brax observation normaliser for observations ``[obs_size]`` (float32)."""
    import jax.numpy as jnp
    from brax.training.acme import running_statistics, specs

    return running_statistics.init_state(specs.Array((int(obs_size),), jnp.dtype("float32")))


def params_to_state(params) -> dict:
    """The state dict of parameters ``(normalizer, policy, value)`` (host arrays)."""
    import jax
    from flax import serialization

    normalizer, policy, value = jax.tree.map(np.asarray, tuple(params))
    return {"normalizer": serialization.to_state_dict(normalizer), "policy": policy, "value": value}


def params_from_state(state: dict, where: str) -> tuple:
    """Parameters ``(normalizer, policy, value)`` of a state dict (:func:`params_to_state`)."""
    if not isinstance(state, dict) or set(state) != {"normalizer", "policy", "value"}:
        raise StoredDataError(f"{where}: expected the normalizer, policy and value parameters, found "
                              f"{sorted(state) if isinstance(state, dict) else type(state).__name__}")
    norm = state["normalizer"]
    mean = norm.get("mean") if isinstance(norm, dict) else None
    if not isinstance(mean, np.ndarray) or mean.ndim != 1:
        raise StoredDataError(f"{where}: the observation normaliser has no vector of means")
    normalizer = _fill(normalizer_template(mean.shape[0]), norm, f"{where} (normalizer)")
    return normalizer, _plain(state["policy"], f"{where}/policy"), _plain(state["value"], f"{where}/value")


def params_bytes(params) -> bytes:
    """The bytes of ``PARAMS_FILE`` for parameters ``(normalizer, policy, value)``."""
    from flax import serialization

    return serialization.msgpack_serialize({"format": PARAMS_FORMAT, **params_to_state(params)})


def params_file(run_dir: str | FsPath) -> FsPath | None:
    """The parameter file of a finished run (data first, then a legacy pickle), or None."""
    for name in (PARAMS_FILE, LEGACY_PARAMS_FILE):
        if (FsPath(run_dir) / name).is_file():
            return FsPath(run_dir) / name
    return None


def read_params(run_dir: str | FsPath, allow_pickle: bool = False) -> tuple[tuple, FsPath]:
    """``((normalizer, policy, value), file)`` of the finished run in ``run_dir``.

    Raises :class:`FileNotFoundError` when it has no parameters, :class:`PickleRefused` for a
    pickle without ``allow_pickle``, :class:`StoredDataError` for anything else unreadable."""
    path = params_file(run_dir)
    if path is None:
        raise FileNotFoundError(f"{run_dir}: no {PARAMS_FILE} (not a finished run)")
    if path.name == LEGACY_PARAMS_FILE:
        loaded = _unpickle(path, allow_pickle)
        if not (isinstance(loaded, tuple) and len(loaded) == 3):
            raise StoredDataError(f"{path}: expected (normalizer, policy, value), found {type(loaded).__name__}")
        return loaded, path
    state = _restore(path)
    if state.get("format") != PARAMS_FORMAT:
        raise StoredDataError(f"{path}: format {state.get('format')!r}, this package reads {PARAMS_FORMAT!r}")
    del state["format"]
    return params_from_state(state, str(path)), path


def learner_params(learner, devices: int):
    """``(normalizer, policy, value)`` host arrays of a learner (a checkpoint's or a live one;
    pmapped over ``devices`` > 1: device 0's copy, all devices hold the same)."""
    import jax

    params = jax.tree.map(np.asarray, jax.device_get((learner.normalizer_params, learner.params.policy,
                                                      learner.params.value)))
    return jax.tree.map(lambda x: x[0], params) if devices > 1 else params


def _leaves(tree) -> tuple[list[str], list]:
    """The names (key paths) and leaves of ``tree``."""
    import jax

    flat = jax.tree_util.tree_flatten_with_path(tree)[0]
    return [jax.tree_util.keystr(path) for path, _ in flat], [leaf for _, leaf in flat]


def checkpoint_bytes(step: int, wall_s: float, devices: int, learner, evaluations: dict) -> bytes:
    """The bytes of a checkpoint: every array of the learner (optimiser, networks, normaliser,
    environment states, keys) with its name in the learner's tree, the parameters ``(normalizer,
    policy, value)`` once more by name (:func:`learner_params`: for evaluating a checkpoint without
    building a learner), the step, the wall time so far [s], the device count and the evaluations
    (nested dicts of floats)."""
    from flax import serialization

    names, arrays = _leaves(learner)
    return serialization.msgpack_serialize({
        "format": CHECKPOINT_FORMAT, "step": int(step), "wall_s": float(wall_s), "devices": int(devices),
        "learner": {"names": names, "arrays": [np.asarray(a) for a in arrays]},
        "params": params_to_state(learner_params(learner, devices)), "evaluations": evaluations})


def read_checkpoint(path: FsPath, allow_pickle: bool = False) -> dict:
    """A checkpoint's dict: ``step``, ``wall_s``, ``devices``, ``evaluations``, ``params``
    (``(normalizer, policy, value)``) and ``learner`` (:func:`learner_from_checkpoint` fills a
    learner with it). A pickled checkpoint of an older run is read only with ``allow_pickle``."""
    if path.read_bytes()[:1] == PICKLE_MAGIC:
        data = _unpickle(path, allow_pickle)
        if not isinstance(data, dict) or data.get("format") != 1:
            raise StoredDataError(f"{path}: not a checkpoint of this package")
        return {**data, "params": learner_params(data["learner"], int(data.get("devices", 1)))}
    data = _restore(path)
    if data.get("format") != CHECKPOINT_FORMAT:
        raise StoredDataError(f"{path}: format {data.get('format')!r}, this package reads {CHECKPOINT_FORMAT!r}")
    missing = {"step", "wall_s", "devices", "learner", "evaluations", "params"} - set(data)
    if missing:
        raise StoredDataError(f"{path}: no {', '.join(sorted(missing))}")
    return {**data, "params": params_from_state(data["params"], str(path))}


def learner_from_checkpoint(template, checkpoint: dict, where: str):
    """A learner of ``template``'s structure (a learner of the same config and device count, or
    its ``jax.eval_shape``: only names, shapes and dtypes are read) with the arrays of a
    checkpoint (:func:`read_checkpoint`), every array's name, shape and dtype checked."""
    import jax

    stored = checkpoint["learner"]
    if not isinstance(stored, dict) or "names" not in stored:  # an older run's pickled learner
        return stored
    names, mine = _leaves(template)
    theirs, arrays = list(stored["names"]), list(stored["arrays"])
    if theirs != names:
        diff = next((f"{a} / {b}" for a, b in zip(names, theirs) if a != b), f"{len(theirs)} / {len(names)} arrays")
        raise StoredDataError(f"{where}: the stored learner does not fit this run's (first difference, expected / "
                              f"stored: {diff})")
    for name, a, b in zip(names, mine, arrays):
        if not isinstance(b, np.ndarray) or a.shape != b.shape or a.dtype != b.dtype:
            got = f"{b.dtype}{list(b.shape)}" if isinstance(b, np.ndarray) else type(b).__name__
            raise StoredDataError(f"{where}: {name} is {got}, this run's {a.dtype}{list(a.shape)}")
    return jax.tree.unflatten(jax.tree.structure(template), arrays)
