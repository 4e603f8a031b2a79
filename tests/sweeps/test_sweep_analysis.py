"""sweep_analysis on hand-made summaries (no training): Pareto front, the paper's tables, errors.
The notebook itself is executed on a real tiny sweep in tests/sweeps/test_sweep_run.py."""

import csv
import json
from pathlib import Path

import numpy as np
import pytest

from mjx_pathtrack.sweeps import analysis as A

COLUMNS = ["point", "n_next", "alpha", "dataset", "run_dir", "return", "end_reached", "success", "stop_time_s",
           "mean_deviation", "max_deviation", "toppra_duration_s", "ratio_to_toppra"]


def write_sweep(directory: Path, rows: list[dict], grid: dict, extra_columns=()) -> Path:
    directory.mkdir(parents=True, exist_ok=True)
    with open(directory / "summary.csv", "w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=COLUMNS + list(extra_columns))
        writer.writeheader()
        writer.writerows(rows)
    (directory / "sweep.json").write_text(json.dumps({"base": {"robot": "iiwa"}, "grid": grid}))
    return directory


def row(name, n_next, alpha, dur, dev, dataset="random", **extra):
    return {"point": name, "n_next": n_next, "alpha": alpha, "dataset": dataset, "run_dir": name, "return": 10 * alpha,
            "end_reached": 1.0, "success": 0.5, "stop_time_s": dur, "mean_deviation": dev,
            "max_deviation": 2 * dev if dev != "" else "", "toppra_duration_s": 2.0,
            "ratio_to_toppra": dur / 2.0 if dur != "" else "", **extra}


def test_pareto_front_keeps_exactly_the_non_dominated_points():
    duration = np.array([1.0, 2.0, 3.0, 2.5, np.nan, 1.0])
    deviation = np.array([0.3, 0.2, 0.1, 0.25, 0.0, 0.3])
    # 3 is dominated by 1 (2.0 <= 2.5, 0.2 <= 0.25); NaN is never on the front; equal points both stay
    assert A.pareto_front(duration, deviation).tolist() == [True, True, True, False, False, True]


def test_tables_from_a_summary(tmp_path):
    rows = [row("a", 5, 1.0, 5.0, 0.05), row("b", 5, 2.0, 4.0, 0.08), row("c", 9, 1.0, 4.5, 0.09),
            row("d", 9, 2.0, "", "")]
    summary = A.load_summary(write_sweep(tmp_path / "s", rows, {"n_next": [5, 9], "alpha": [1.0, 2.0]}))
    assert A.swept_fields(summary) == ["n_next", "alpha"]
    assert np.isnan(summary["stop_time_s"][3]) and summary["point"].tolist() == ["a", "b", "c", "d"]

    t2 = A.tradeoff_table(summary)
    assert [r[0] for r in t2.rows] == ["n_next=5, alpha=2", "n_next=9, alpha=1", "n_next=5, alpha=1",
                                       "n_next=9, alpha=2"]  # by duration, missing last
    assert [r[-1] for r in t2.rows] == [True, False, True, False]  # c is dominated by b
    assert "| n_next=5, alpha=2 | 4 | 0.08 |" in t2.markdown()

    t3 = A.knots_table(summary)
    assert [r[:3] for r in t3.rows] == [[5.0, 2, 4.5], [9.0, 2, 4.5]]  # NaN durations are left out of the mean
    assert t3.rows[0][3] == pytest.approx(0.065)

    t6 = A.toppra_table(summary)
    assert t6.rows[0][3] == 2.5 and t6.rows[0][4] == pytest.approx(40.0)
    assert np.isnan(t6.rows[3][3]) and "78.5" in t6.note
    with pytest.raises(A.AnalysisError, match="target_point"):
        A.generalization_table(summary, "target_point")


def test_generalization_table_per_training_dataset(tmp_path):
    extra = {f"on_target_point_{k}": v for k, v in
             {"stop_time_s": 6.0, "mean_deviation": 0.1, "max_deviation": 0.2, "end_reached": 0.5,
              "success": 0.25}.items()}
    rows = [row("r", 8, 1.0, 4.0, 0.05, **extra), row("t", 8, 1.0, 5.0, 0.07, dataset="target_point", **extra)]
    summary = A.load_summary(write_sweep(tmp_path / "s", rows, {"dataset": ["random", "target_point"]}, extra))
    table = A.generalization_table(summary, "target_point")
    assert [r[0] for r in table.rows] == ["random → own test split", "random → target_point",
                                          "target_point → own test split"]
    assert table.rows[1][2:] == [6.0, 0.1, 0.2, 0.5, 0.25] and table.rows[2][2] == 5.0


def test_missing_sweep_and_missing_dataset_are_explained(tmp_path):
    with pytest.raises(A.AnalysisError, match="no summary.csv"):
        A.load_summary(tmp_path)
    summary = A.load_summary(write_sweep(tmp_path / "s", [row("a", 8, 1.0, 4.0, 0.05)], {"alpha": [1.0]}))
    with pytest.raises(A.AnalysisError, match="does not exist yet.*generate it"):
        A.generalization_table(summary, "no_such_dataset")
    with pytest.raises(A.AnalysisError, match="does not vary n_next"):
        A.knots_table({k: v for k, v in summary.items() if k != "n_next"})
    with pytest.raises(A.AnalysisError, match="episode0.npz"):
        A.load_episode(tmp_path)


def test_plots_draw_points_front_and_joints(tmp_path):
    import matplotlib

    matplotlib.use("Agg")
    rows = [row("a", 8, 1.0, 5.0, 0.05), row("b", 8, 2.0, 4.0, 0.08), row("c", 8, 3.0, 4.5, 0.09)]
    summary = A.load_summary(write_sweep(tmp_path / "s", rows, {"alpha": [1.0, 2.0, 3.0]}))
    ax = A.plot_tradeoff(summary)
    front = [l for l in ax.get_lines() if l.get_label() == "Pareto front"][0]
    assert front.get_xdata().tolist() == [4.0, 5.0]
    T, n = 3, 7
    episode = {"dt": np.float64(0.1), "executed": np.zeros((T, 25, n)), "v": np.ones((T, n)), "a": np.zeros((T, n)),
               "vel": 2 * np.ones(n), "acc": np.ones(n), "path_index": np.int64(4)}
    fig = A.plot_episode(episode)
    velocity = fig.axes[1].get_lines()[0].get_ydata()
    assert len(fig.axes[0].get_lines()) == n and velocity[0] == 0.0 and np.allclose(velocity[1:], 0.5)
    positions_t = fig.axes[0].get_lines()[0].get_xdata()
    assert positions_t[0] == 0.0 and positions_t[-1] == pytest.approx(0.3) and len(positions_t) == 1 + 3 * 24


def _write_sweep_with_configs(directory: Path, rows: list[dict], grid: dict, configs: list[dict]) -> Path:
    columns = [c for c in COLUMNS if c not in ("n_next", "alpha", "dataset")]
    columns[1:1] = list(grid)
    with_grid = [{k: r[k] for k in columns} for r in rows]
    directory.mkdir(parents=True, exist_ok=True)
    with open(directory / "summary.csv", "w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=columns)
        writer.writeheader()
        writer.writerows(with_grid)
    (directory / "sweep.json").write_text(json.dumps({"base": {}, "grid": grid}))
    for r, config in zip(rows, configs):
        (directory / r["run_dir"]).mkdir()
        (directory / r["run_dir"] / "config.json").write_text(json.dumps(config))
    return directory


def test_combine_joins_sweeps_reads_fixed_fields_from_configs_and_keeps_a_shared_point_once(tmp_path):
    alphas = [row("alpha=2.0", 8, 2.0, 4.0, 0.06), row("alpha=3.0", 8, 3.0, 3.8, 0.08),
              row("alpha=4.5", 8, 4.5, 3.7, 0.09)]
    knots = [row("n_next=4", 4, 3.0, 4.4, 0.07), row("n_next=8", 8, 3.0, 3.9, 0.08)]
    table2 = _write_sweep_with_configs(tmp_path / "t2", alphas, {"alpha": [2.0, 3.0, 4.5]},
                                       [{"n_next": 8, "alpha": r["alpha"]} for r in alphas])
    table3 = _write_sweep_with_configs(tmp_path / "t3", knots, {"n_next": [4, 8]},
                                       [{"n_next": r["n_next"], "alpha": 3.0} for r in knots])
    s2, s3 = A.load_summary(table2), A.load_summary(table3)
    assert "n_next" not in s2 and "alpha" not in s3
    both = A.combine([s2, s3])
    assert A.swept_fields(both) == ["alpha", "n_next"]
    # alpha=3 / n_next=8 is the same configuration in both sweeps: kept once, from the first
    assert both["point"].tolist() == ["t2/alpha=2.0", "t2/alpha=3.0", "t2/alpha=4.5", "t3/n_next=4"]
    assert both["n_next"].tolist() == [8.0, 8.0, 8.0, 4.0] and both["alpha"].tolist() == [2.0, 3.0, 4.5, 3.0]
    assert both["stop_time_s"].tolist() == [4.0, 3.8, 3.7, 4.4]
    assert all((Path(d) / "config.json").is_file() for d in both["run_dir"])
    t2 = A.tradeoff_table(both)
    assert t2.rows[0][0] == "alpha=4.5, n_next=8" and [r[-1] for r in t2.rows] == [True, True, True, False]
    with pytest.raises(A.AnalysisError, match="no sweeps"):
        A.combine([])


def test_paper_rows_beside_ours():
    paper = A.paper_table2()
    assert [r[1] for r in paper.rows] == [4.76, 4.28, 4.08] and [r[2] for r in paper.rows] == [2.7, 3.3, 3.6]
    summary = {"n_next": np.array([4.0, 6.0, 8.0, 5.0]), "stop_time_s": np.array([5.0, 4.5, 4.0, 4.8]),
               "mean_deviation": np.full(4, 0.08), "max_deviation": np.full(4, 0.15), "end_reached": np.ones(4)}
    t3 = A.knots_table(summary)
    # the paper counts the knots in the state, N + 1: its 5 / 7 / 9 are N = 4 / 6 / 8; N = 5 has no paper row
    assert [r[6] for r in t3.rows] == [5, 6, 7, 9]
    assert [r[7] for r in t3.rows][0] == 5.20 and np.isnan(t3.rows[1][7]) and t3.rows[2][7] == 4.52
    assert t3.rows[3][7:] == [4.28, 3.3] and "N + 1" in " ".join(t3.columns)
