"""The run directory and exact checkpoints: what a run writes, when a directory may take a run
(``--resume`` / ``--overwrite``), and the whole learner state saved after each evaluation
interval (the newest ``KEEP_CHECKPOINTS`` kept) so that a resumed run ends exactly as an
uninterrupted one.
"""

from __future__ import annotations

import os
from pathlib import Path as FsPath

from mjx_pathtrack.config.stored import learner_params  # noqa: F401  (re-exported: training's parameters)
from mjx_pathtrack.fileio import atomic_write_bytes


class RunDirError(ValueError):
    """The run directory cannot be used as asked (holds another run, is a file, not writable)."""


#: files and folders of a run directory that this package writes
RUN_FILES = ("config.json", "progress.csv", "checkpoints", "params.msgpack", "params.pkl", "report.json", "export", "tensorboard",
             "data", "eval")


def prepare_run_dir(run_dir: FsPath, resume: bool, overwrite: bool) -> bool:
    """Check that ``run_dir`` can take this run (nothing is written). Returns whether the
    directory holds a previous run. Raises :class:`RunDirError`: a file, not writable, or a run
    that neither ``resume`` nor ``overwrite`` was asked for."""
    if run_dir.exists() and not run_dir.is_dir():
        raise RunDirError(f"--out {run_dir}: is a file, not a directory")
    parent = next((p for p in [run_dir, *run_dir.parents] if p.exists()), None)
    if parent is None or not parent.is_dir() or not os.access(parent, os.W_OK | os.X_OK):
        raise RunDirError(f"--out {run_dir}: cannot create or write it ({parent} is not a writable directory)")
    held = [name for name in RUN_FILES if (run_dir / name).exists()]
    if held and not (resume or overwrite):
        raise RunDirError(f"--out {run_dir}: holds a training run ({', '.join(held)}); use --resume to continue it, "
                          f"--overwrite to replace it, or choose another --out")
    if resume and overwrite:
        raise RunDirError("--resume and --overwrite exclude each other")
    return bool(held)


def clear_run_dir(run_dir: FsPath) -> None:
    """Remove what this package wrote into ``run_dir`` (``--overwrite``)."""
    import shutil

    for name in RUN_FILES:
        target = run_dir / name
        if target.is_dir():
            shutil.rmtree(target)
        elif target.exists():
            target.unlink()


CHECKPOINT_SUFFIX = ".ckpt"


#: checkpoints kept per run (older ones are deleted)
KEEP_CHECKPOINTS = 3


def checkpoint_path(checkpoints: FsPath, step: int) -> FsPath:
    return checkpoints / f"{step:012d}{CHECKPOINT_SUFFIX}"


def checkpoint_steps(checkpoints: FsPath) -> list[int]:
    """The env steps of the checkpoints in folder ``checkpoints``, ascending (none: ``[]``)."""
    if not checkpoints.is_dir():
        return []
    names = (f.name[:-len(CHECKPOINT_SUFFIX)] for f in checkpoints.iterdir() if f.name.endswith(CHECKPOINT_SUFFIX))
    return sorted(int(n) for n in names if n.isdigit())


def latest_checkpoint(checkpoints: FsPath) -> tuple[FsPath, int] | None:
    """The newest checkpoint file and the env steps it stands for, or None. Files are written
    atomically, so any file found is complete."""
    steps = checkpoint_steps(checkpoints)
    return (checkpoint_path(checkpoints, steps[-1]), steps[-1]) if steps else None


def save_checkpoint(checkpoints: FsPath, step: int, wall_s: float, devices: int, learner, evaluations: dict
                    ) -> FsPath:
    """Write the checkpoint of ``step`` as data (:func:`~mjx_pathtrack.config.stored.checkpoint_bytes`:
    the learner's host arrays, the wall time so far [s], the device count, the evaluations); keep
    the newest few."""
    from mjx_pathtrack.config.stored import checkpoint_bytes

    path = checkpoint_path(checkpoints, step)
    atomic_write_bytes(path, checkpoint_bytes(step, wall_s, devices, learner, evaluations))
    old = sorted(f for f in checkpoints.iterdir() if f.name.endswith(CHECKPOINT_SUFFIX))
    for f in old[:-KEEP_CHECKPOINTS]:
        f.unlink()
    return path


def load_checkpoint(path: FsPath, allow_pickle: bool = False) -> dict:
    """A checkpoint as :func:`~mjx_pathtrack.config.stored.read_checkpoint` reads it (data; an
    older run's pickle only with ``allow_pickle``); :class:`RunDirError` if it cannot be read."""
    from mjx_pathtrack.config.stored import StoredDataError, read_checkpoint

    try:
        return read_checkpoint(path, allow_pickle)
    except StoredDataError as e:
        raise RunDirError(str(e)) from e
