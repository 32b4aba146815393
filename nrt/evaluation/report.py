"""Accuracy versus time across runs: what ``nrt-report`` draws and tabulates.

Each run's TensorBoard scalars give the curves: a metric logged at step s is placed at
the training seconds ``time/wall_s`` of that step (interpolated between logged steps;
validation time is not counted, see :class:`nrt.callbacks.WallClock`). Runs are labelled
by the Hydra overrides that differ between them (``.hydra/overrides.yaml``).
"""

from __future__ import annotations

import csv
import json
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import yaml

from nrt.errors import NrtError
from nrt.run_dirs import RUN_FILE

CURVES = ("val/mse_sigma_a_x100", "val/mse_sigma_s_x100", "val/mse_sigma_t_x100",
          "val/mse_g_x100", "val/psnr", "eval/psnr_novel")
"""Metrics drawn, in panel order (those no run logged are left out). ``val/psnr`` is each
stage's own renderer, so it is drawn only when every run is of one stage; runs of several
stages are compared by ``eval/psnr_novel``, the same Mitsuba re-render for all
(:class:`nrt.callbacks.RerenderEvaluation`)."""
OWN_RENDERER = ("val/psnr",)
LOWER_IS_BETTER = {m: m.startswith("val/mse") for m in CURVES}
IGNORED_OVERRIDES = ("hydra.", "paths.", "render.progress", "trainer.enable_progress_bar",
                     "init.ea_ckpt", "budget.dpt.steps", "budget.rte.steps", "budget.ea.steps")
"""Overrides that do not tell runs apart (paths, display, the step caps of budget runs)."""


@dataclass
class RunCurves:
    path: Path
    stage: str
    overrides: list[str]
    curves: dict[str, tuple[np.ndarray, np.ndarray]] = field(default_factory=dict)
    evaluation: dict[str, float] = field(default_factory=dict)
    label: str = ""
    seconds: float = 0.0
    """Training seconds at the end of the run (``time/wall_s``)."""

    def final(self, metric: str) -> str:
        return f"{self.curves[metric][1][-1]:.3f}" if metric in self.curves else "-"


def find_runs(paths: list[str | Path]) -> list[Path]:
    """Run folders (with ``run.json``) given directly or anywhere below ``paths``
    (a multirun sweep folder holds one per job)."""
    runs: list[Path] = []
    for p in map(Path, paths):
        if not p.is_dir():
            raise NrtError(f"'{p}' is not a folder. Pass run folders of nrt-train or a folder "
                           "holding them (e.g. outputs/multirun/<timestamp>).")
        found = [p] if (p / RUN_FILE).is_file() else sorted(
            q.parent for q in p.rglob(RUN_FILE) if "eval" not in q.relative_to(p).parts)
        if not found:
            raise NrtError(f"No run of nrt-train under '{p}' (no {RUN_FILE} found). Runs "
                           "made before nrt-report existed lack it; train anew.")
        runs += found
    return list(dict.fromkeys(runs))


def _scalars(run: Path) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    out: dict[str, tuple[list, list]] = {}
    for folder in sorted({e.parent for e in run.glob("tensorboard/**/events.out.tfevents*")}):
        acc = EventAccumulator(str(folder), size_guidance={"scalars": 0})
        acc.Reload()
        for tag in acc.Tags()["scalars"]:
            steps, values = out.setdefault(tag, ([], []))
            for event in acc.Scalars(tag):
                steps.append(event.step)
                values.append(event.value)
    result = {}
    for tag, (steps, values) in out.items():
        order = np.argsort(steps, kind="stable")
        result[tag] = (np.asarray(steps)[order], np.asarray(values, float)[order])
    return result


def _short(override: str) -> str:
    """``key=1234.5678`` -> ``key=1235`` (long floats make unreadable labels)."""
    key, _, value = override.partition("=")
    try:
        number = float(value)
    except ValueError:
        return override
    return f"{key}={number:.4g}" if "." in value else override


def latest_evaluation(run: Path) -> dict[str, float]:
    """Metrics of the run's newest ``nrt-eval`` (empty if never evaluated)."""
    files = sorted(run.glob("eval/*/metrics.json"))
    return json.loads(files[-1].read_text())["metrics"] if files else {}


def read_run(run: Path) -> RunCurves:
    info = json.loads((run / RUN_FILE).read_text())
    overrides_file = run / ".hydra" / "overrides.yaml"
    overrides = yaml.safe_load(overrides_file.read_text()) if overrides_file.is_file() else []
    overrides = [_short(o) for o in overrides or [] if not o.startswith(IGNORED_OVERRIDES)]
    scalars = _scalars(run)
    result = RunCurves(run, info["stage"], overrides, evaluation=latest_evaluation(run))
    if "time/wall_s" not in scalars:
        return result
    wall_steps, wall = scalars["time/wall_s"]
    result.seconds = float(wall.max())
    for metric in CURVES:
        if metric in scalars:
            steps, values = scalars[metric]
            result.curves[metric] = (np.interp(steps, wall_steps, wall), values)
    return result


def label_runs(runs: list[RunCurves]) -> None:
    """Label each run by its overrides that not all runs share (with the stage when the
    stages differ); identical runs by their folder name."""
    common = set.intersection(*(set(r.overrides) for r in runs)) if runs else set()
    stages = {r.stage for r in runs}
    for r in runs:
        parts = [o for o in r.overrides if o not in common and not o.startswith("stage=")]
        head = [r.stage] if len(stages) > 1 or not parts else []
        r.label = " ".join(head + parts) or r.path.name
    seen: dict[str, int] = {}
    for r in runs:
        seen[r.label] = seen.get(r.label, 0) + 1
    for r in runs:
        if seen[r.label] > 1:
            r.label = f"{r.label} ({r.path.name})"


def frontier_share(runs: list[RunCurves], metric: str, points: int = 200) -> dict[str, float]:
    """Fraction of the (log-spaced) time axis on which each run is the most accurate,
    comparing each run's latest value at each time (the accuracy/time frontier); moments
    when several runs tie, such as their common starting point, are not counted."""
    have = [r for r in runs if metric in r.curves and len(r.curves[metric][0]) > 1]
    if not have:
        return {}
    t_max = max(r.curves[metric][0][-1] for r in have)
    t_min = min(r.curves[metric][0][r.curves[metric][0] > 0].min(initial=t_max) for r in have)
    grid = np.geomspace(max(t_min, 1e-3), max(t_max, 2e-3), points)
    sign = 1.0 if LOWER_IS_BETTER[metric] else -1.0
    table = np.full((len(have), points), np.inf)
    for i, r in enumerate(have):
        t, v = r.curves[metric]
        idx = np.searchsorted(t, grid, side="right") - 1
        ok = (idx >= 0) & (grid <= t[-1] * 1.0001)
        table[i, ok] = sign * v[idx[ok]]
    best, low = np.argmin(table, 0), table.min(0)
    ties = (np.abs(table - low) <= 1e-9 * np.abs(low)).sum(0) > 1  # e.g. the shared start
    valid = np.isfinite(low) & ~ties
    if not valid.any():
        return {r.label: 0.0 for r in have}
    return {have[i].label: float(np.mean(best[valid] == i)) for i in range(len(have))}


def write_csv(runs: list[RunCurves], path: Path) -> Path:
    with open(path, "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(["label", "stage", "run", "metric", "wall_s", "value"])
        for r in runs:
            for metric, (t, v) in r.curves.items():
                for ti, vi in zip(t, v, strict=True):
                    w.writerow([r.label, r.stage, str(r.path), metric, f"{ti:.3f}", f"{vi:.6g}"])
    return path


SUMMARY_COLUMNS = {"seconds": None, "sigma_a": "val/mse_sigma_a_x100",
                   "sigma_s": "val/mse_sigma_s_x100", "sigma_t": "val/mse_sigma_t_x100",
                   "g": "val/mse_g_x100", "psnr": "val/psnr"}
EVAL_COLUMNS = {"psnr_novel": "psnr_novel", "ssim_novel": "ssim_novel",
                "psnr_seen": "psnr_seen"}


def summary_markdown(runs: list[RunCurves], shares: dict[str, float]) -> str:
    """Final values per run (MSE x100 at the end of training, held-out PSNR of the stage's
    own renderer when all runs are of one stage, and the newest nrt-eval's
    novel-illumination PSNR/SSIM when there is one)."""
    head = ["setting", *SUMMARY_COLUMNS, *EVAL_COLUMNS, "frontier share (sigma_t)"]
    lines = ["| " + " | ".join(head) + " |", "|---" + "|---:" * (len(head) - 1) + "|"]
    drawn = drawn_metrics(runs)
    for r in runs:
        cells = [r.label, f"{r.seconds:.0f}"]
        cells += [r.final(m) if m in drawn else "-" for m in list(SUMMARY_COLUMNS.values())[1:]]
        cells += [f"{r.evaluation[k]:.3f}" if k in r.evaluation else "-"
                  for k in EVAL_COLUMNS.values()]
        cells.append(f"{shares.get(r.label, 0.0):.2f}")
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def drawn_metrics(runs: list[RunCurves]) -> list[str]:
    """The metrics of :data:`CURVES` that compare these runs by one measurement: without a
    stage's own renderer's PSNR when the runs are of several stages."""
    mixed = len({r.stage for r in runs}) > 1
    return [m for m in CURVES if not (mixed and m in OWN_RENDERER)]


def plot(runs: list[RunCurves], path: Path) -> Path:
    """One panel per metric, one curve per run; seconds on a log axis (0 on its linear
    stretch), MSE on a log axis."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    metrics = [m for m in drawn_metrics(runs) if any(m in r.curves for r in runs)]
    if not metrics:
        raise NrtError("None of the runs logged accuracy metrics against time/wall_s "
                       f"({', '.join(CURVES)}); they need ground truth and a validation.")
    fig, axes = plt.subplots(1, len(metrics), figsize=(4.2 * len(metrics), 3.6), squeeze=False)
    for ax, metric in zip(axes[0], metrics, strict=True):
        for r in runs:
            if metric in r.curves:
                t, v = r.curves[metric]
                ax.plot(t, v, marker="o", markersize=3, label=r.label)
        ax.set_xscale("symlog", linthresh=1.0)
        if LOWER_IS_BETTER[metric]:
            ax.set_yscale("log")
        ax.set_xlabel("training seconds")
        ax.set_title(metric.removeprefix("val/"))
        ax.grid(True, which="both", alpha=0.3)
    handles = {}
    for ax in axes[0]:
        for line in ax.get_lines():
            handles.setdefault(line.get_label(), line)
    fig.legend(handles.values(), handles.keys(), loc="lower center", fontsize=8,
               ncol=min(len(handles), 4), frameon=False)
    fig.tight_layout(rect=(0, 0.06 * ((len(handles) + 3) // 4) + 0.02, 1, 1))
    fig.savefig(path, dpi=120)
    plt.close(fig)
    return path
