"""Add ``export/policy.onnx`` to run directories trained before exports held one.

For each run: the deterministic policy rebuilt from the run's ``config.json`` and ``params.msgpack``
(as ``evaluate.py RUN`` does), converted to ONNX with jax2onnx and checked against the run's own
``export/policy.jaxexport`` on 10,000 observations; ``policy.onnx`` is written if they agree
within 1e-5, the manifest's ``onnx`` entry (the figure, or why there is no file) in any case. New runs get the file from ``train.py`` itself.

    python scripts/attach_onnx.py policies/iiwa policies/ball_on_plate ...
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import mjx_pathtrack  # noqa: E402

mjx_pathtrack.prepare_xla()
import jax  # noqa: E402
import jax.numpy as jnp  # noqa: E402


def main(argv=None) -> int:
    from mjx_pathtrack.deploy.export import ExportError, attach_onnx
    from mjx_pathtrack.evaluation.report import EvaluationError, load_policy_source

    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("runs", nargs="+", metavar="RUN")
    args = parser.parse_args(argv)
    failed = 0
    for run in args.runs:
        try:
            source = load_policy_source(run)
            if source.kind != "run":
                raise EvaluationError(f"{run} is an export; give its run directory (config.json + params.msgpack)")
            key = jax.random.PRNGKey(0)
            entry = attach_onnx(Path(run) / "export", lambda obs: jnp.clip(source.policy(obs, key), -1.0, 1.0))
        except (EvaluationError, ExportError) as e:
            print(f"{run}: {e}", file=sys.stderr)
            failed += 1
            continue
        if entry["file"] is None:
            print(f"{run}: no ONNX graph: {entry['reason']} (recorded in the manifest)", file=sys.stderr)
            failed += 1
        else:
            print(f"{run}/export/policy.onnx: max |action difference| {entry['max_abs_difference']:.2e} against "
                  f"policy.jaxexport on {entry['checked_observations']} observations")
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
