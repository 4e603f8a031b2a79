"""Analysis of a sweep directory (:mod:`mjx_pathtrack.sweeps.run`): the tables of paper 000 and plots.

The notebook ``notebooks/tradeoff_sweeps.ipynb`` is a thin front end to these functions:

* :func:`load_summary` reads ``summary.csv`` into columns (NumPy arrays; strings stay strings);
  :func:`combine` joins the summaries of several sweeps (e.g. Table II's and Table III's) into one;
* :func:`pareto_front` marks the points no other point beats in both duration and deviation;
* :func:`tradeoff_table` (Table II), :func:`knots_table` (Table III), :func:`generalization_table`
  (Table IV), :func:`toppra_table` (Table VI) return :class:`Table` objects (rows + Markdown);
* :func:`plot_tradeoff` (duration vs mean deviation with the Pareto front) and
  :func:`plot_episode` (one evaluation episode's joint trajectories, ``episode0.npz``).

Durations are the mean time [s] until the robot stopped after reaching the end of the path (over
the evaluation episodes that did); deviations are joint-space [rad] (the paper's tables give
Cartesian ones). Missing values (no episode stopped, no TOPP-RA baseline) are NaN.
"""

from __future__ import annotations

import csv
import dataclasses
import json
from pathlib import Path as FsPath
from typing import Sequence

import numpy as np

#: paper 000 Table VI: TOPP-RA / policy duration [%] (iiwa, random paths)
PAPER_TOPPRA_PERCENT = {"iiwa": 78.5}
#: paper 000 Table II (iiwa, random paths): weighting of R_l against R_d, duration until stopped
#: [s], Cartesian position deviation mean / max / final [cm]
PAPER_TABLE2 = (("length < deviation", 4.76, 2.7, 6.4, 2.3), ("length ≈ deviation", 4.28, 3.3, 7.5, 2.7),
                ("length > deviation", 4.08, 3.6, 8.0, 3.1))
#: paper 000 Table III (iiwa, random paths): knots in the state -> duration until stopped [s],
#: Cartesian position deviation mean / max / final [cm]. The state holds the last knot passed and
#: the next N (``n_next``), i.e. N + 1 knots: the papers' 9-knot row is their N = 8 network (the
#: same 4.28 s as their Table I), so N + 1 is compared with the paper's count.
PAPER_TABLE3 = {5: (5.20, 2.5, 5.6, 2.8), 7: (4.52, 3.4, 7.5, 3.0), 9: (4.28, 3.3, 7.5, 2.7)}


class AnalysisError(ValueError):
    """A sweep directory or column the analysis needs is missing; the message says which."""


def load_summary(sweep_dir: str | FsPath) -> dict[str, np.ndarray]:
    """Columns of ``sweep_dir/summary.csv``: numeric columns as float arrays (empty cells NaN),
    others as string arrays; plus ``sweep_dir`` itself under the key ``"_dir"`` (a string)."""
    file = FsPath(sweep_dir) / "summary.csv"
    if not file.is_file():
        raise AnalysisError(f"no summary.csv in {sweep_dir} (run the sweep first: python train.py --sweep FILE)")
    with open(file, newline="") as f:
        rows = list(csv.DictReader(f))
    if not rows:
        raise AnalysisError(f"{file} has no finished points yet")
    out: dict[str, np.ndarray] = {}
    for key in rows[0]:
        values = [r[key] for r in rows]
        try:
            out[key] = np.array([float(v) if v != "" else np.nan for v in values])
        except ValueError:
            out[key] = np.array(values)
    out["_dir"] = np.array(str(sweep_dir))
    return out


def _sweep_meta(summary: dict[str, np.ndarray]) -> dict:
    meta = FsPath(str(summary["_dir"])) / "sweep.json"
    return json.loads(meta.read_text()) if meta.is_file() else {}


def swept_fields(summary: dict[str, np.ndarray]) -> list[str]:
    """The grid fields of the sweep (from ``sweep.json``; of a :func:`combine`-d summary: of all
    its sweeps), in file order."""
    if "_grid" in summary:
        return [str(k) for k in summary["_grid"] if k in summary]
    return [k for k in _sweep_meta(summary).get("grid", {}) if k in summary]


def _point_config(sweep_dir: FsPath, run_dir: str) -> dict:
    """The flat options (``--name`` -> value) of a point's ``config.json`` ({} if missing)."""
    from mjx_pathtrack.config.run import TrainConfig

    file = sweep_dir / run_dir / "config.json"
    return TrainConfig.from_json(file.read_text()).flat() if file.is_file() else {}


def combine(summaries: Sequence[dict[str, np.ndarray]]) -> dict[str, np.ndarray]:
    """One summary of the points of several sweeps: the union of their grid fields, a field a
    sweep did not vary read from each point's ``config.json`` (NaN if missing), columns one sweep
    lacks NaN / empty. A point whose grid values equal an earlier point's (the same configuration
    reached by two sweeps) is kept once, the first time. ``run_dir`` becomes a path from the
    first sweep's directory's parent (``SWEEP/POINT``) so that :func:`load_episode` still finds it."""
    if not summaries:
        raise AnalysisError("no sweeps to combine")
    grid: list[str] = []
    for summary in summaries:
        grid += [f for f in swept_fields(summary) if f not in grid]
    columns: list[str] = []
    for summary in summaries:
        columns += [k for k in summary if not k.startswith("_") and k not in columns]
    rows: list[dict] = []
    seen: set = set()
    for summary in summaries:
        where = FsPath(str(summary["_dir"]))
        for i in range(len(summary["point"])):
            row = {k: summary[k][i] for k in summary if not k.startswith("_")}
            fixed = [f for f in grid if f not in row]
            config = _point_config(where, str(row["run_dir"])) if fixed and "run_dir" in row else {}
            for f in fixed:
                value = config.get(f, np.nan)
                row[f] = float(value) if isinstance(value, (int, float)) and not isinstance(value, bool) else value
            key = tuple(str(row[f]) for f in grid)
            if key in seen:
                continue
            seen.add(key)
            row["point"] = f"{where.name}/{row['point']}"
            if "run_dir" in row:
                row["run_dir"] = str(where / str(row["run_dir"]))
            rows.append(row)
    out: dict[str, np.ndarray] = {}
    for key in columns:
        values = [r.get(key, np.nan) for r in rows]
        numeric = all(isinstance(v, (int, float, np.integer, np.floating)) and not isinstance(v, bool) for v in values)
        out[key] = np.array(values, float) if numeric else np.array(["" if (isinstance(v, float) and np.isnan(v))
                                                                    else str(v) for v in values])
    out["_dir"] = summaries[0]["_dir"]
    out["_grid"] = np.array(grid)
    return out


def pareto_front(duration: np.ndarray, deviation: np.ndarray) -> np.ndarray:
    """Bool ``[P]``: point i is on the front if it has finite values and no other point is at least
    as good in both (lower duration and lower deviation) and better in one."""
    d, e = np.asarray(duration, float), np.asarray(deviation, float)
    ok = np.isfinite(d) & np.isfinite(e)
    front = ok.copy()
    for i in np.flatnonzero(ok):
        dominated = ok & (d <= d[i]) & (e <= e[i]) & ((d < d[i]) | (e < e[i]))
        front[i] = not dominated.any()
    return front


@dataclasses.dataclass
class Table:
    """A result table: ``title``, ``columns``, ``rows`` (lists of cells), an optional ``note``."""

    title: str
    columns: list[str]
    rows: list[list]
    note: str = ""

    def markdown(self) -> str:
        lines = [f"**{self.title}**", "", "| " + " | ".join(self.columns) + " |",
                 "|" + "---|" * len(self.columns)]
        lines += ["| " + " | ".join(_fmt(c) for c in r) + " |" for r in self.rows]
        if self.note:
            lines += ["", self.note]
        return "\n".join(lines)

    def _repr_markdown_(self) -> str:  # Jupyter shows it as a table
        return self.markdown()


def _fmt(x) -> str:
    if isinstance(x, (float, np.floating)):
        return "–" if not np.isfinite(x) else f"{x:.3g}" if abs(x) < 1000 else f"{x:,.0f}"
    if isinstance(x, (bool, np.bool_)):
        return "yes" if x else ""
    return str(x)


def _col(summary, key: str) -> np.ndarray:
    if key not in summary:
        raise AnalysisError(f"summary.csv has no column {key!r}")
    return summary[key]


def _label(summary, i: int, fields: Sequence[str]) -> str:
    return ", ".join(f"{k}={_fmt(summary[k][i])}" for k in fields) or str(summary["point"][i])


def tradeoff_table(summary: dict[str, np.ndarray]) -> Table:
    """Table II: every point's duration, mean/max deviation, end-reached rate, arc progress and
    return, sorted by duration, with its Pareto-front membership (duration vs mean deviation)."""
    fields = swept_fields(summary)
    dur, dev = _col(summary, "stop_time_s"), _col(summary, "mean_deviation")
    front = pareto_front(dur, dev)
    order = np.lexsort((dev, np.where(np.isfinite(dur), dur, np.inf)))
    progress = summary.get("progress", np.full(len(dur), np.nan))
    rows = [[_label(summary, i, fields), dur[i], dev[i], summary["max_deviation"][i], summary["end_reached"][i],
             progress[i], summary["return"][i], bool(front[i])] for i in order]
    note = "" if front.any() else ("No point has both a duration and a deviation (no evaluation episode stopped at "
                                   "the end): no Pareto front. The arc progress column shows how far they got.")
    return Table("Table II: duration vs deviation", ["point", "duration [s]", "mean dev [rad]", "max dev [rad]",
                                                     "end reached", "progress", "return", "Pareto"], rows, note)


def _mean_by(summary, key: str, columns: Sequence[str]) -> list[list]:
    values = _col(summary, key)
    rows = []
    for v in sorted(set(values.tolist())):
        sel = values == v
        rows.append([v, int(sel.sum())] + [_nanmean(summary[c][sel]) for c in columns])
    return rows


def _nanmean(x: np.ndarray) -> float:
    x = np.asarray(x, float)
    return float(np.nanmean(x)) if np.isfinite(x).any() else float("nan")


def knots_table(summary: dict[str, np.ndarray]) -> Table:
    """Table III: duration and deviation per number of knots N (``n_next``), averaged over the
    other swept values."""
    if "n_next" not in summary:
        raise AnalysisError("the sweep does not vary n_next (add it to the grid for Table III)")
    cols = ["stop_time_s", "mean_deviation", "max_deviation", "end_reached"]
    rows = _mean_by(summary, "n_next", cols)
    for r in rows:
        knots = int(r[0]) + 1 if np.isfinite(r[0]) else np.nan  # the paper's count (PAPER_TABLE3)
        paper = PAPER_TABLE3.get(knots, (np.nan,) * 4)
        r += [knots, paper[0], paper[1]]
    return Table("Table III: knots N in the observation", ["N", "points", "duration [s]", "mean dev [rad]",
                                                           "max dev [rad]", "end reached", "knots in the state (N + 1)",
                                                           "paper: duration [s]", "paper: Cart. mean dev [cm]"],
                 rows, "Paper 000 Table III counts the knots in the state: the last one passed and the next N.")


def paper_table2() -> Table:
    """Paper 000 Table II (iiwa, random paths), to show beside :func:`tradeoff_table`."""
    return Table("Paper 000 Table II (iiwa, random paths; deviations Cartesian)",
                 ["weighting", "duration [s]", "Cart. mean dev [cm]", "Cart. max dev [cm]", "Cart. final dev [cm]"],
                 [list(r) for r in PAPER_TABLE2],
                 "Its policies: 195 M env steps each (45 h); mean joint deviation 0.11 rad at 4.28 s (Table I).")


def generalization_table(summary: dict[str, np.ndarray], test_dataset: str = "target_point") -> Table:
    """Table IV: per training dataset, the metrics on its own test split and on ``test_dataset``'s
    (columns ``on_<test_dataset>_*``), averaged over the points trained on it."""
    prefix = f"on_{test_dataset}_"
    if not any(k.startswith(prefix) for k in summary):
        from mjx_pathtrack.paths import datasets

        base = _sweep_meta(summary).get("base", {})
        robot, root = base.get("robot", "iiwa"), base.get("dataset_root")
        where = datasets.dataset_dir(robot, test_dataset, root)
        if not (where / "test.npz").is_file():
            raise AnalysisError(f"the {test_dataset!r} dataset does not exist yet ({where}/test.npz missing): "
                                f"generate it with python -m mjx_pathtrack.paths generate --robot {robot} "
                                f"--kind {test_dataset}, then re-run the sweep with 'test_datasets: [{test_dataset}]'")
        raise AnalysisError(f"no results on the {test_dataset!r} dataset in this sweep: add "
                            f"'test_datasets: [{test_dataset}]' to the sweep file and re-run it")
    trained = summary["dataset"] if "dataset" in summary else None
    names = sorted(set(trained.tolist())) if trained is not None else [None]
    metrics = ["stop_time_s", "mean_deviation", "max_deviation", "end_reached", "success"]
    rows = []
    for name in names:
        sel = np.ones(len(summary["point"]), bool) if name is None else trained == name
        label = "training dataset" if name is None else name
        rows.append([f"{label} → own test split", int(sel.sum())] + [_nanmean(summary[m][sel]) for m in metrics])
        if name != test_dataset:
            rows.append([f"{label} → {test_dataset}", int(sel.sum())]
                        + [_nanmean(summary[prefix + m][sel]) for m in metrics])
    return Table(f"Table IV: generalisation to {test_dataset}", ["trained → tested", "points", "duration [s]",
                                                               "mean dev [rad]", "max dev [rad]", "end reached",
                                                               "success"], rows)


def toppra_table(summary: dict[str, np.ndarray], robot: str = "iiwa") -> Table:
    """Table VI: per point, the policy's duration, the TOPP-RA duration of the same sub-paths, the
    policy/TOPP-RA ratio (episodes that stopped) and TOPP-RA's share of the policy's time [%]."""
    fields = swept_fields(summary)
    ratio = _col(summary, "ratio_to_toppra")
    rows = [[_label(summary, i, fields), summary["stop_time_s"][i], summary["toppra_duration_s"][i], ratio[i],
             100.0 / ratio[i] if np.isfinite(ratio[i]) and ratio[i] > 0 else float("nan")]
            for i in range(len(ratio))]
    paper = PAPER_TOPPRA_PERCENT.get(robot)
    note = f"Paper 000 Table VI ({robot}, random paths): TOPP-RA needs {paper} % of the policy's time." if paper else ""
    return Table("Table VI: policy vs TOPP-RA (velocity/acceleration limits only)",
                 ["point", "policy duration [s]", "TOPP-RA duration [s]", "ratio policy/TOPP-RA", "TOPP-RA / policy [%]"],
                 rows, note)


def plot_tradeoff(summary: dict[str, np.ndarray], ax=None):
    """Scatter of duration [s] vs mean deviation [rad] per point, Pareto front as a line."""
    import matplotlib.pyplot as plt

    if ax is None:
        _, ax = plt.subplots(figsize=(6, 4))
    fields = swept_fields(summary)
    dur, dev = summary["stop_time_s"], summary["mean_deviation"]
    ok = np.isfinite(dur) & np.isfinite(dev)
    ax.scatter(dur[ok], dev[ok], c="tab:blue", label="points")
    for i in np.flatnonzero(ok):
        ax.annotate(_label(summary, i, fields), (dur[i], dev[i]), fontsize=7, xytext=(3, 3), textcoords="offset points")
    front = pareto_front(dur, dev)
    if front.any():
        order = np.argsort(dur[front])
        ax.plot(dur[front][order], dev[front][order], "-o", c="tab:red", label="Pareto front")
    if not ok.any():
        ax.text(0.5, 0.5, "no point stopped at the end in evaluation", ha="center", va="center",
                transform=ax.transAxes)
    ax.set_xlabel("duration until stopped [s]")
    ax.set_ylabel("mean joint deviation [rad]")
    if ok.any():
        ax.legend(loc="best")
    return ax


def load_episode(run_dir: str | FsPath) -> dict[str, np.ndarray]:
    """The recorded evaluation episode 0 of a point (``episode0.npz``)."""
    file = FsPath(run_dir) / "episode0.npz"
    if not file.is_file():
        raise AnalysisError(f"no episode0.npz in {run_dir} (the point is not finished)")
    with np.load(file) as data:
        return {k: data[k] for k in data.files}


def plot_episode(episode: dict[str, np.ndarray], title: str = ""):
    """Joint positions [rad] at every executed sub-step (start included), and velocity /
    acceleration at the decision instants (from rest at t = 0) normalised by their limits, against
    time [s]. Returns the figure."""
    import matplotlib.pyplot as plt

    dt = float(episode["dt"])
    exe = episode["executed"]  # [T, S+1, n]
    T, S1, n = exe.shape
    fig, axes = plt.subplots(3, 1, figsize=(8, 7), sharex=True)
    if T == 0:
        axes[0].text(0.5, 0.5, "empty episode", ha="center", transform=axes[0].transAxes)
        return fig
    t_sub = (np.arange(T)[:, None] + np.arange(1, S1)[None] / (S1 - 1)).reshape(-1) * dt
    q = exe[:, 1:].reshape(-1, n)
    t_dec = dt * np.arange(T + 1)  # episodes start at rest: v = a = 0 at t = 0
    v = np.concatenate([np.zeros((1, n)), episode["v"]])
    a = np.concatenate([np.zeros((1, n)), episode["a"]])
    for j in range(n):
        axes[0].plot(np.concatenate([[0.0], t_sub]), np.concatenate([exe[0, :1, j], q[:, j]]), label=f"joint {j + 1}")
        axes[1].plot(t_dec, v[:, j] / episode["vel"][j])
        axes[2].plot(t_dec, a[:, j] / episode["acc"][j])
    axes[0].set_ylabel("position [rad]")
    axes[1].set_ylabel("v / v_max")
    axes[2].set_ylabel("a / a_max")
    for ax in axes[1:]:
        ax.axhline(1, c="k", lw=0.5, ls="--")
        ax.axhline(-1, c="k", lw=0.5, ls="--")
    axes[2].set_xlabel("time [s]")
    axes[0].legend(ncol=4, fontsize=7)
    fig.suptitle(title or f"evaluation episode 0 (dataset path {int(episode['path_index'])})")
    fig.tight_layout()
    return fig
