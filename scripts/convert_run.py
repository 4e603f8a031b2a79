"""Rewrite run directories written before parameters were stored as data: their pickles become
MessagePack files (mjx_pathtrack/config/stored.py), so that evaluating, resuming or warm-starting
from them no longer needs --allow-pickle.

    python scripts/convert_run.py runs/old_run [more runs ...]

Opening a pickle runs whatever code it carries: convert only runs you made yourself or trust.
Per run: ``params.pkl`` -> ``params.msgpack`` (then the pickle is removed), and every pickled
``checkpoints/*.ckpt`` rewritten in place as data (resume stays exact: the same arrays). Each file
is written whole before the old one goes (a kill leaves the old file or the new one). Runs already
converted are left as they are. Exit status 1 if a run could not be converted.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path


def convert(run: Path) -> list[str]:
    """Convert one run directory; returns what was done (lines)."""
    import jax
    import numpy as np

    from mjx_pathtrack.config import run_dir as C
    from mjx_pathtrack.config import stored
    from mjx_pathtrack.fileio import atomic_write_bytes

    done = []
    legacy = run / stored.LEGACY_PARAMS_FILE
    if legacy.is_file() and not (run / stored.PARAMS_FILE).is_file():
        params, _ = stored.read_params(run, allow_pickle=True)
        atomic_write_bytes(run / stored.PARAMS_FILE, stored.params_bytes(params))
        again, _ = stored.read_params(run)   # the data file now comes first: read it back
        same = jax.tree.map(lambda a, b: bool(np.array_equal(np.asarray(a), np.asarray(b))), params, again)
        if not all(jax.tree.leaves(same)):
            (run / stored.PARAMS_FILE).unlink()
            raise ValueError(f"{legacy}: the converted parameters differ from the pickle's; the pickle is kept")
        legacy.unlink()
        done.append(f"{legacy.name} -> {stored.PARAMS_FILE}")
    folder = run / "checkpoints"
    for step in C.checkpoint_steps(folder):
        path = C.checkpoint_path(folder, step)
        if path.read_bytes()[:1] != stored.PICKLE_MAGIC:
            continue
        old = stored.read_checkpoint(path, allow_pickle=True)
        atomic_write_bytes(path, stored.checkpoint_bytes(old["step"], old["wall_s"], int(old["devices"]), old["learner"],
                                                         old["evaluations"]))
        done.append(f"checkpoints/{path.name} rewritten as data")
    return done


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("runs", nargs="+", metavar="RUN")
    args = p.parse_args(argv)
    failed = False
    for run in map(Path, args.runs):
        if not (run / "config.json").is_file():
            print(f"{run}: not a run directory (no config.json)", file=sys.stderr)
            failed = True
            continue
        try:
            done = convert(run)
        except (OSError, ValueError) as e:
            print(f"{run}: not converted: {e}", file=sys.stderr)
            failed = True
            continue
        print(f"{run}: " + ("; ".join(done) if done else "nothing to convert (already data)"))
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
