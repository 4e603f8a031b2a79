"""Training data of a run: regenerate a larger train split deterministically when the dataset's
committed one is too small (the repository commits small train splits only).

``ensure_train_paths(robot, kind, num_train, root, data_dir)``: if ``<root>/<robot>/<kind>/
train.npz`` holds at least ``num_train`` paths (or ``num_train <= 0``), nothing happens and
``root`` is returned. Otherwise ``num_train`` train paths are generated with the dataset's own
recipe (``config.json``: kind, ``source.seed`` and the generator parameters in ``source``; the
train split uses ``seed`` exactly as ``datasets generate`` does) into ``<data_dir>/<robot>/<kind>/``
together with a copy of the test split and a config.json, all written atomically, and
``data_dir`` is returned. A data directory that already holds the same recipe and count is
reused (resume). ``max_dis_between_knots`` (the observation scale) is kept from the original
dataset so that evaluation on the committed test split sees the same observations; the config
records the regenerated train split's own largest spacing beside it.
"""

from __future__ import annotations

import json
import os
from typing import Callable

from mjx_pathtrack.paths import datasets
from mjx_pathtrack.fileio import atomic_write


def ensure_train_paths(robot: str, kind: str, num_train: int, root=None, data_dir=None,
                       log: Callable[[str], None] | None = print) -> str | os.PathLike | None:
    """The dataset root to train from (see module docstring)."""
    from mjx_pathtrack.paths import generate

    if num_train <= 0:
        return root
    config = datasets.read_config(robot, kind, root)
    directory = datasets.dataset_dir(robot, kind, root)
    have = len(datasets.load_split(robot, kind, "train", root)) if (directory / "train.npz").is_file() else 0
    if have >= num_train:
        return root
    if data_dir is None:
        raise datasets.DatasetError(f"{robot}/{kind}: train split has {have} paths, {num_train} wanted, "
                                    f"and no data directory to regenerate into")
    source = config.get("source", {})
    if kind not in generate.KINDS or "seed" not in source:
        raise datasets.DatasetError(f"{directory}: cannot regenerate {num_train} train paths (kind {kind!r} has no "
                                    f"generator or config.json has no source.seed; it has {have})")
    params = generate.source_params(kind, source)
    recipe = {"seed": int(source["seed"]), "params": params, "num_train": int(num_train),
              "from": str(directory.resolve())}
    target = datasets.dataset_dir(robot, kind, data_dir)
    existing = target / "config.json"
    if existing.is_file() and json.loads(existing.read_text()).get("regenerated") == recipe \
            and (target / "train.npz").is_file() and (target / "test.npz").is_file():
        if log:
            log(f"train data: reusing {num_train} regenerated {robot}/{kind} train paths in {target}")
        return data_dir
    if log:
        log(f"train data: {robot}/{kind} train split has {have} paths < {num_train}; regenerating {num_train} "
            f"deterministically (seed {recipe['seed']}, {params}) into {target}")
    paths, _ = generate.generate_split(robot, kind, num_train, recipe["seed"], **params)
    datasets.save_split(target / "train.npz", paths)
    test = directory / "test.npz"
    if test.is_file():
        atomic_write(target / "test.npz", lambda f: f.write(test.read_bytes()))
    new = dict(config, num_train=num_train, regenerated=recipe,
               train_max_dis_between_knots=datasets.max_dis_between_knots([paths]))
    datasets.write_config(existing, new)
    if log:
        log(f"train data: wrote {num_train} train paths to {target} (largest knot spacing "
            f"{new['train_max_dis_between_knots']:.3f}, observation scale kept at {config['max_dis_between_knots']:.3f})")
    return data_dir

