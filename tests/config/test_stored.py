"""Parameters and checkpoints as data: loading a run directory never runs code from it."""

from __future__ import annotations

import json
import pathlib
import pickle
import shutil
import subprocess
import sys
from pathlib import Path

import jax
import numpy as np
import pytest

from mjx_pathtrack.config import run_dir as C
from mjx_pathtrack.config import stored

REPO = Path(__file__).resolve().parents[2]
SHIPPED = REPO / "policies" / "iiwa"


class _Payload:
    """Unpickling this creates the file ``marker``: the code a crafted pickle could run instead."""

    def __init__(self, marker: Path):
        self.marker = marker

    def __reduce__(self):
        return pathlib.Path.touch, (pathlib.Path(self.marker),)


def _crafted_run(where: Path) -> tuple[Path, Path]:
    """A run directory whose ``params.pkl`` and checkpoint are crafted pickles; returns it and the
    marker file their code would create."""
    marker = where.parent / f"{where.name}_ran"
    (where / "checkpoints").mkdir(parents=True)
    shutil.copy(SHIPPED / "config.json", where / "config.json")
    payload = pickle.dumps(_Payload(marker))
    (where / stored.LEGACY_PARAMS_FILE).write_bytes(payload)
    C.checkpoint_path(where / "checkpoints", 100).write_bytes(payload)
    return where, marker


def test_shipped_parameters_are_data_and_read_back_exactly():
    params, path = stored.read_params(SHIPPED)
    assert path.name == stored.PARAMS_FILE and not (SHIPPED / stored.LEGACY_PARAMS_FILE).exists()
    normalizer, policy, value = params
    manifest = json.loads((SHIPPED / "export" / "manifest.json").read_text())
    # (the normaliser also covers the privileged critic's extra inputs after the policy's)
    assert normalizer.mean.shape[0] >= manifest["observation_size"]
    assert policy["params"]["Dense_0"]["kernel"].shape[-1] == manifest["action_size"]
    assert int(normalizer.count.lo) > 0  # the trained normaliser, not the empty template
    # arrays of their own, as unpickled (MessagePack's are read-only views of its buffer)
    editable = jax.tree.leaves((policy, value)) + [normalizer.mean, normalizer.std, normalizer.summed_variance]
    assert all(x.flags.writeable for x in editable)
    again = stored.params_from_state(jax.tree.map(np.asarray, stored.params_to_state(params)), "again")
    for a, b in zip(jax.tree.leaves(params), jax.tree.leaves(again)):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
    assert stored.params_bytes(params) == path.read_bytes()  # the same bytes once more


@pytest.mark.parametrize("entrance", ["evaluate", "warm start", "resume", "checkpoint evaluation"])
def test_a_crafted_pickle_does_not_run(tmp_path, entrance):
    """Every entrance that opens a run directory someone sent: evaluation (run directory or one of
    its checkpoints), --init-from and --resume refuse the pickles by name and pointing to
    --allow-pickle, and the pickles' code does not run."""
    from mjx_pathtrack.config.run import TrainConfig
    from mjx_pathtrack.evaluation import report as R
    from mjx_pathtrack.rl import warm_start as warm

    run, marker = _crafted_run(tmp_path / "sent")
    if entrance == "evaluate":
        with pytest.raises(R.EvaluationError, match="is a Python pickle.*--allow-pickle"):
            R.load_policy_source(str(run))
    elif entrance == "checkpoint evaluation":
        with pytest.raises(R.EvaluationError, match="is a Python pickle.*--allow-pickle"):
            R.load_policy_source(str(run), checkpoint="latest")
    elif entrance == "warm start":
        with pytest.raises(C.RunDirError, match="--init-from: .*is a Python pickle.*--allow-pickle"):
            warm.read_source(run)
    else:
        from mjx_pathtrack.rl.training import train

        config = TrainConfig.from_json((run / "config.json").read_text())
        with pytest.raises(C.RunDirError, match="is a Python pickle.*--allow-pickle"):
            train(config, run, resume=True, verbose=False)
    assert not marker.exists()


def test_the_crafted_pickle_runs_when_allowed(tmp_path):
    """The opt-in does open pickles (so the refusals above are what keeps the code from running);
    what comes out is still checked."""
    from mjx_pathtrack.evaluation import report as R

    run, marker = _crafted_run(tmp_path / "trusted")
    with pytest.raises(R.EvaluationError, match="expected \\(normalizer, policy, value\\)"):
        R.load_policy_source(str(run), allow_pickle=True)
    assert marker.exists()


def test_evaluate_cli_refuses_a_pickle_in_one_line(tmp_path):
    run, marker = _crafted_run(tmp_path / "cli")
    result = subprocess.run([sys.executable, "evaluate.py", str(run)], cwd=REPO, capture_output=True, text=True,
                            timeout=300)
    assert result.returncode == 2, result.stdout + result.stderr
    line = result.stderr.strip().splitlines()[-1]
    assert line.startswith("evaluate.py: error: ") and "is a Python pickle" in line and "--allow-pickle" in line
    assert not marker.exists()


def test_files_that_do_not_fit_are_refused_by_name(tmp_path):
    params, _ = stored.read_params(SHIPPED)
    state = stored.params_to_state(params)
    (tmp_path / stored.PARAMS_FILE).write_bytes(b"\x93\x01\x02\x03")  # a msgpack list, not a map
    with pytest.raises(stored.StoredDataError, match="not a file of this package"):
        stored.read_params(tmp_path)
    from flax import serialization

    (tmp_path / stored.PARAMS_FILE).write_bytes(serialization.msgpack_serialize({"format": "other/9", **state}))
    with pytest.raises(stored.StoredDataError, match="format 'other/9'"):
        stored.read_params(tmp_path)
    bad = jax.tree.map(lambda x: x, state)
    bad["policy"]["params"]["Dense_0"]["bias"] = np.arange(3)  # integers where parameters are floats
    with pytest.raises(stored.StoredDataError, match="policy/params/Dense_0/bias: a ndarray where"):
        stored.params_from_state(bad, "bad")
    with pytest.raises(stored.StoredDataError, match="expected the normalizer, policy and value"):
        stored.params_from_state({"policy": state["policy"]}, "bad")
    # a checkpoint's learner is checked name by name and shape by shape against this run's
    template = {"a": np.zeros(3, np.float32), "b": np.zeros((), np.uint32)}
    names = ["['a']", "['b']"]
    with pytest.raises(stored.StoredDataError, match=r"\['a'\] is float32\[4\], this run's float32\[3\]"):
        stored.learner_from_checkpoint(template, {"learner": {"names": names, "arrays": [np.zeros(4, np.float32),
                                                                                          np.zeros((), np.uint32)]}}, "c")
    with pytest.raises(stored.StoredDataError, match="does not fit this run's"):
        stored.learner_from_checkpoint(template, {"learner": {"names": ["['a']", "['c']"], "arrays": [
            np.zeros(3, np.float32), np.zeros((), np.uint32)]}}, "c")
    filled = stored.learner_from_checkpoint(template, {"learner": {"names": names, "arrays": [
        np.ones(3, np.float32), np.full((), 7, np.uint32)]}}, "c")
    assert filled["a"].tolist() == [1, 1, 1] and int(filled["b"]) == 7


def test_convert_run_rewrites_an_old_pickled_run_as_data(tmp_path):
    """``scripts/convert_run.py``: an older run's params.pkl and pickled checkpoint become data
    with the same arrays; the run then loads without --allow-pickle."""
    from brax.training.agents.ppo import losses as ppo_losses

    from mjx_pathtrack.rl.ppo import Learner

    params, _ = stored.read_params(SHIPPED)
    run = tmp_path / "old"
    (run / "checkpoints").mkdir(parents=True)
    shutil.copy(SHIPPED / "config.json", run / "config.json")
    (run / stored.LEGACY_PARAMS_FILE).write_bytes(pickle.dumps(params))
    normalizer, policy, value = params
    learner = Learner(optimizer_state=(np.zeros(2, np.float32),), params=ppo_losses.PPONetworkParams(policy, value),
                      normalizer_params=normalizer, env_state=np.arange(5), key=np.array([1, 2], np.uint32))
    old = {"format": 1, "step": 100, "wall_s": 2.5, "devices": 1, "learner": learner,
           "evaluations": {"latest": {"eval/return": 1.5}}}
    C.checkpoint_path(run / "checkpoints", 100).write_bytes(pickle.dumps(old))
    with pytest.raises(stored.PickleRefused):
        stored.read_params(run)
    result = subprocess.run([sys.executable, "scripts/convert_run.py", str(run)], cwd=REPO, capture_output=True,
                            text=True, timeout=300)
    assert result.returncode == 0, result.stderr
    assert "params.pkl -> params.msgpack" in result.stdout and "rewritten as data" in result.stdout
    assert not (run / stored.LEGACY_PARAMS_FILE).exists()
    again, _ = stored.read_params(run)
    for a, b in zip(jax.tree.leaves(params), jax.tree.leaves(again)):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
    checkpoint = stored.read_checkpoint(C.checkpoint_path(run / "checkpoints", 100))
    assert checkpoint["step"] == 100 and checkpoint["wall_s"] == 2.5 and checkpoint["evaluations"] == old["evaluations"]
    restored = stored.learner_from_checkpoint(jax.tree.map(np.zeros_like, learner), checkpoint, "converted")
    for a, b in zip(jax.tree.leaves(learner), jax.tree.leaves(restored)):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
    again = subprocess.run([sys.executable, "scripts/convert_run.py", str(run)], cwd=REPO, capture_output=True,
                           text=True, timeout=300)
    assert again.returncode == 0 and "nothing to convert" in again.stdout
