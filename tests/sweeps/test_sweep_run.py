"""sweep.py on one tiny 2x2 grid (trained once, vmapped): summary, run directories, resume, the
train.py front end, bad sweep files, and the analysis notebook executed on the result."""

import csv
import json
import shutil
import sys
from pathlib import Path

import numpy as np
import pytest
import yaml

import mjx_pathtrack  # noqa: F401
from mjx_pathtrack.paths import datasets
from mjx_pathtrack.sweeps import run as sweep
from mjx_pathtrack.sweeps import spec as sweep_spec
from mjx_pathtrack.config.run import TrainConfig
from mjx_pathtrack.config.stored import read_params

REPO = Path(__file__).resolve().parents[2]
TINY = dict(num_envs=8, num_timesteps=640, unroll_length=5, batch_size=8, num_minibatches=2,
            num_updates_per_batch=1, num_evals=2, eval_episodes=4, policy_layers=[16], value_layers=[16],
            duration=4.0)


def write_spec(path: Path, **data) -> Path:
    path.write_text(yaml.safe_dump(data))
    return path


@pytest.fixture(scope="module")
def tiny_sweep(tmp_path_factory):
    """A 2x2 grid over alpha and beta, trained together, evaluated on the random test split and on
    an exact copy of it under another name (the extra test dataset)."""
    root = tmp_path_factory.mktemp("splines")
    src = datasets.dataset_dir("iiwa", "random")
    shutil.copytree(src, root / "iiwa" / "random")
    shutil.copytree(src, root / "iiwa" / "random_copy")
    base = {**TINY, "dataset_root": str(root)}
    spec_file = write_spec(tmp_path_factory.mktemp("spec") / "tiny.yaml", base=base,
                           grid={"alpha": [1.0, 2.0], "beta": [0.5, 0.9]}, test_datasets=["random_copy"],
                           eval_episodes=4, vectorize=True)
    out = tmp_path_factory.mktemp("sweep")
    spec = sweep_spec.load_spec(spec_file)
    summary = sweep.run_sweep(spec, out, verbose=False)
    return spec_file, spec, out, summary


def read_rows(file: Path) -> list[dict]:
    with open(file, newline="") as f:
        return list(csv.DictReader(f))


def test_summary_has_one_row_per_point_with_swept_values_and_metrics(tiny_sweep):
    _, spec, out, summary = tiny_sweep
    rows = read_rows(summary)
    assert [(float(r["alpha"]), float(r["beta"])) for r in rows] == [(1.0, 0.5), (1.0, 0.9), (2.0, 0.5), (2.0, 0.9)]
    columns = set(rows[0])
    assert columns >= {"point", "run_dir", "trainer", "train_seconds", *sweep.METRICS, *sweep.AUDIT}
    assert columns >= {f"on_random_copy_{m}" for m in sweep.METRICS}
    for r in rows:
        assert r["trainer"] == "vmapped"
        for key in ("return", "mean_deviation", "max_deviation", "end_reached", "progress", "toppra_duration_s"):
            assert np.isfinite(float(r[key])), key
        assert float(r["toppra_duration_s"]) > 0
        assert 0.0 <= float(r["end_reached"]) <= 1.0
        assert max(float(r[k]) for k in sweep.AUDIT) <= 1.0 + 1e-6  # safe action space: no limit violated
        # the copy of the test split gives the same episodes, hence the same metrics
        assert float(r["on_random_copy_return"]) == pytest.approx(float(r["return"]), rel=1e-5)
    # each point trained and evaluated with its own reward weights
    assert len({r["return"] for r in rows}) == 4


def test_each_point_has_a_run_directory(tiny_sweep):
    _, spec, out, summary = tiny_sweep
    for point, r in zip(sweep_spec.grid_points(spec), read_rows(summary)):
        run = out / r["run_dir"]
        assert r["point"] == point.name == run.name
        assert TrainConfig.from_json((run / "config.json").read_text()) == point.config
        assert point.config.env.reward.distance == float(r["alpha"]) and point.config.env.reward.max_deviation == float(r["beta"])
        params = read_params(run)[0]
        assert len(params) == 3  # Brax layout: normalizer, policy, value
        assert (run / "export" / "manifest.json").is_file()
        assert len(read_rows(run / "progress.csv")) >= 1
        record = json.loads((run / sweep.METRICS_FILE).read_text())
        assert record["values"] == {"alpha": point.config.env.reward.distance, "beta": point.config.env.reward.max_deviation}
        with np.load(run / sweep.EPISODE_FILE) as ep:
            assert ep["p"].shape[1] == 7 and ep["executed"].shape[0] == ep["p"].shape[0] >= 1


def test_resume_skips_finished_points_and_redoes_only_the_missing_one(tiny_sweep, tmp_path, monkeypatch):
    _, spec, out, summary = tiny_sweep
    before = summary.read_bytes()
    copy = tmp_path / "sweep"
    shutil.copytree(out, copy)
    missing = sweep_spec.grid_points(spec)[2]
    record = json.loads((copy / missing.name / sweep.METRICS_FILE).read_text())
    (copy / missing.name / sweep.METRICS_FILE).unlink()
    calls = []

    def fake_train(point, run_dir, verbose):  # stands in for Brax training: reuse the trained params
        calls.append(point.name)
        return read_params(run_dir)[0], record["train_seconds"]

    def fake_evaluate(points, params, evaluation, spec):
        assert [p.name for p in points] == [missing.name]
        with np.load(copy / missing.name / sweep.EPISODE_FILE) as ep:
            return [record["metrics"]], [{k: ep[k] for k in ep.files}]

    monkeypatch.setattr(sweep, "_train_sequential", fake_train)
    monkeypatch.setattr(sweep, "evaluate_group", fake_evaluate)
    monkeypatch.setattr(sweep, "_train_vectorized", lambda *a: pytest.fail("a finished point was retrained"))
    result = sweep.run_sweep(spec, copy, vectorize=False, verbose=False)
    assert calls == [missing.name]
    rows, old = read_rows(result), list(csv.DictReader(before.decode().splitlines()))
    assert [r["point"] for r in rows] == [r["point"] for r in old]
    assert rows[2]["trainer"] == "brax" and rows[2]["return"] == old[2]["return"]
    # everything finished now: nothing is trained again
    calls.clear()
    sweep.run_sweep(spec, copy, vectorize=False, verbose=False)
    assert calls == []


def test_train_py_sweep_flag_reports_a_finished_sweep(tiny_sweep, capsys):
    spec_file, _, out, summary = tiny_sweep
    sys.path.insert(0, str(REPO))
    try:
        import train
    finally:
        sys.path.remove(str(REPO))
    assert train.main(["--sweep", str(spec_file), "--out", str(out)]) == 0
    printed = capsys.readouterr().out
    assert "4 already done" in printed
    assert summary.read_text().splitlines()[0] in printed


def test_notebook_executes_on_the_sweep(tiny_sweep, monkeypatch):
    import nbformat  # the 'notebook' extra (also in 'test')
    from nbclient import NotebookClient

    _, _, out, _ = tiny_sweep
    monkeypatch.setenv("SWEEP_DIR", str(out))
    monkeypatch.setenv("MPLBACKEND", "module://matplotlib_inline.backend_inline")  # figures as PNG outputs
    nb = nbformat.read(REPO / "notebooks" / "tradeoff_sweeps.ipynb", as_version=4)
    NotebookClient(nb, timeout=300, kernel_name="python3",
                   resources={"metadata": {"path": str(REPO / "notebooks")}}).execute()
    outputs = [o for c in nb.cells if c.cell_type == "code" for o in c.outputs]
    assert not [o for o in outputs if o.output_type == "error"]
    text = "\n".join(str(o.get("text", "")) + str(o.get("data", {}).get("text/markdown", "")) for o in outputs)
    assert "4 finished points" in text and "Table II" in text and "Table VI" in text
    assert "Table III not available" in text and "Table IV not available" in text
    assert sum("image/png" in o.get("data", {}) for o in outputs) == 2  # trade-off plot, joint trajectories


# -- sweep files --------------------------------------------------------------------------------

@pytest.mark.parametrize("data, message", [
    ({"grid": {"alpha": [1.0]}, "bogus": 1}, "unknown key"),
    ({"grid": {"alfa": [1.0]}}, "unknown TrainConfig field"),
    ({"base": {"num_envs": 1.5}}, "num_envs = 1.5 is not a valid int"),
    ({"grid": {"alpha": 1.0}}, "alpha must be a non-empty list"),
    ({"grid": {"alpha": []}}, "alpha must be a non-empty list"),
    ({"grid": {"seed": [0, 0]}}, "duplicate values"),
    ({"grid": {"dt": ["fast"]}}, "dt = 'fast' is not a valid float"),
    ({"base": {"alpha": 1.0}, "grid": {"alpha": [2.0]}}, "in both base and grid"),
    ({"eval_episodes": 0}, "eval_episodes must be a positive integer"),
    ({"vectorize": "yes"}, "vectorize must be true or false"),
    ({"test_datasets": [3]}, "test_datasets must be a list"),
    ({"base": {"policy_layers": [0]}}, "positive layer sizes"),
    ([1, 2], "expected a mapping"),
])
def test_bad_sweep_file_is_rejected_with_a_clear_error(tmp_path, data, message):
    file = tmp_path / "bad.yaml"
    file.write_text(yaml.safe_dump(data))
    with pytest.raises(sweep_spec.SweepError, match=message):
        sweep_spec.load_spec(file)


def test_unreadable_or_missing_files_and_datasets(tmp_path, capsys):
    with pytest.raises(sweep_spec.SweepError, match="no sweep file"):
        sweep_spec.load_spec(tmp_path / "none.yaml")
    bad = tmp_path / "bad.yaml"
    bad.write_text("grid: {alpha: [1.0\n")
    with pytest.raises(sweep_spec.SweepError, match="invalid YAML"):
        sweep_spec.load_spec(bad)
    spec_file = write_spec(tmp_path / "s.yaml", grid={"alpha": [1.0]}, test_datasets=["no_such_set"])
    with pytest.raises(sweep_spec.SweepError, match="iiwa/no_such_set: no train split"):
        sweep.run_sweep(sweep_spec.load_spec(spec_file), tmp_path / "out", verbose=False)
    assert sweep.main([str(bad)]) == 2
    assert "invalid YAML" in capsys.readouterr().err


def test_grid_points_are_the_cartesian_product_in_file_order():
    spec = sweep_spec.parse_spec({"base": {"num_envs": 16}, "grid": {"n_next": [5, 9], "alpha": [1, 2.5], "seed": [3]}})
    points = sweep_spec.grid_points(spec)
    assert [p.name for p in points] == ["n_next=5_alpha=1.0_seed=3", "n_next=5_alpha=2.5_seed=3",
                                        "n_next=9_alpha=1.0_seed=3", "n_next=9_alpha=2.5_seed=3"]
    assert all(p.config.ppo.num_envs == 16 for p in points)
    assert points[3].config.env.n_next == 9 and points[3].config.env.reward.distance == 2.5 and isinstance(points[3].config.env.reward.distance, float)
    # points differing only in alpha/seed form one group (trainable together), n_next splits them
    assert [[p.name for p in g] for g in sweep.groups(points)] == [[p.name for p in points[:2]],
                                                                   [p.name for p in points[2:]]]
    assert sweep_spec.grid_points(sweep_spec.parse_spec({}))[0].name == "base"


def test_the_xla_flag_for_mjx_physics_is_wanted_only_by_sweeps_that_step_mjx(tmp_path):
    """A kinematic sweep trains with XLA's default CPU emitters, like a kinematic train.py run
    (faster, and its points equal those runs); one MJX point, or a file that cannot be read,
    asks for the fusion-emitter flag."""
    kinematic = write_spec(tmp_path / "k.yaml", grid={"alpha": [1.0, 2.0]})
    mixed = write_spec(tmp_path / "m.yaml", grid={"executor": ["kinematic", "mjx"]})
    assert sweep_spec.steps_mjx_physics(kinematic) is False
    assert sweep_spec.steps_mjx_physics(mixed) is True
    assert sweep_spec.steps_mjx_physics(tmp_path / "missing.yaml") is True
    (tmp_path / "bad.yaml").write_text("grid: {alfa: [1.0]}")
    assert sweep_spec.steps_mjx_physics(tmp_path / "bad.yaml") is True


def test_changed_sweep_file_does_not_silently_reuse_another_run(tiny_sweep, tmp_path):
    _, spec, out, _ = tiny_sweep
    copy = tmp_path / "sweep"
    shutil.copytree(out, copy)
    changed = sweep_spec.parse_spec({"base": {**TINY, "dataset_root": spec.base["dataset_root"], "num_timesteps": 1280},
                                "grid": {"alpha": [1.0, 2.0], "beta": [0.5, 0.9]}})
    with pytest.raises(sweep_spec.SweepError, match="another configuration"):
        sweep.run_sweep(changed, copy, verbose=False)


def test_module_cli_help_mentions_the_sweep_file_format(capsys):
    with pytest.raises(SystemExit) as exit_info:
        sweep.main(["--help"])
    printed = capsys.readouterr().out
    assert exit_info.value.code == 0 and "grid:" in printed and "summary.csv" in printed and "--sequential" in printed
