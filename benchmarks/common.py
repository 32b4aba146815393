"""Helpers shared by the benchmarks: nrt's real configs composed outside a Hydra app, and
nrt's commands run through the real CLI with their runs and metrics found again."""

from __future__ import annotations

import argparse
import csv
import os
import subprocess
import sys
import time
from pathlib import Path

from hydra import compose, initialize_config_dir
from omegaconf import DictConfig, OmegaConf

from nrt.cli.common import CONFIG_DIR, register_resolvers
from nrt.data.render import dataset_name
from nrt.run_dirs import LAST_CKPT, RESUMED_PREFIX, read_run_info, run_dataset

SCENES = {
    "default": [],
    "default_seed1": ["scene.seed=1", "scene.name=default_seed1"],
    "default_seed2": ["scene.seed=2", "scene.name=default_seed2"],
    "default_seed3": ["scene.seed=3", "scene.name=default_seed3"],
    "varying_g": ["scene=varying_g"],
    "heldout": ["scene=heldout"],
    "heldout2": ["scene=heldout2"],
    "heldout3": ["scene=heldout3"],
    "heldout4": ["scene=heldout4"],
}
"""The benchmark scenes by name: their overrides of the default scene."""
TUNING_SCENES = ("default", "default_seed1", "default_seed2", "default_seed3")
"""The only scenes any default of nrt (stage 2's or the baseline's) is chosen on."""
BLIND_SCENES = ("heldout", "heldout2", "heldout3", "heldout4")
"""Scenes written once and never tuned on: they only report how the defaults carry over."""
TRAINING = ("model", "stage", "data", "losses", "scene", "seed")
"""The sections of a run's config that decide what it trains (the rest: where it writes,
how it logs); ``model`` holds the start (``init.ea_ckpt``)."""


def add_budget_arguments(parser: argparse.ArgumentParser, budget_s: float,
                         every_s: float) -> None:
    """The options of an equal-time run: ``--budget-s`` training seconds per method, the
    property MSE every ``--every-s`` training seconds (outside the clock), ``--preset``."""
    parser.add_argument("--budget-s", type=float, default=budget_s)
    parser.add_argument("--every-s", type=float, default=every_s)
    parser.add_argument("--preset", default="cpu")


def compose_train(overrides: list[str]) -> DictConfig:
    """The ``nrt-train`` config with ``overrides``, as the CLI would compose it."""
    register_resolvers()
    with initialize_config_dir(config_dir=str(CONFIG_DIR), version_base="1.3"):
        return compose("train", overrides=overrides)


def output_dir() -> Path:
    """nrt's output folder (``NRT_OUTPUT_DIR``, else ``outputs``), absolute: its
    ``datasets/`` is the dataset cache every benchmark run shares."""
    return Path(os.environ.get("NRT_OUTPUT_DIR", "outputs")).resolve()


def run_cli(command: str, args: list[str], out: Path) -> float:
    """``python -m nrt.cli.<command> args`` writing its runs under ``out``; exits with the
    command's error output when it fails. Returns its wall seconds (start-up included)."""
    cmd = [sys.executable, "-m", f"nrt.cli.{command}", *args]
    start = time.perf_counter()
    proc = subprocess.run(cmd, env={**os.environ, "NRT_OUTPUT_DIR": str(out)},
                          capture_output=True, text=True)
    if proc.returncode != 0:
        sys.exit(f"{' '.join(cmd)} failed:\n{proc.stderr[-3000:]}")
    return time.perf_counter() - start


def train(stage: str, out: Path, preset: str, overrides: list[str],
          logger: str = "[tensorboard,csv]", resume: Path | None = None,
          data_dir: Path | None = None) -> tuple[Path, float]:
    """``nrt-train stage=<stage> preset=<preset>`` through the CLI, runs under ``out``, the
    datasets from ``data_dir`` (default: the shared cache of :func:`output_dir`); the new run
    folder (with ``resume``, a run folder under ``out``: that run continued in place) and the
    wall seconds."""
    before = set(out.glob(f"*/{stage}/*"))
    data_dir = output_dir() / "datasets" if data_dir is None else data_dir
    wall = run_cli("train", [f"stage={stage}", f"preset={preset}", f"logger={logger}",
                             f"paths.data_dir={data_dir}",
                             "trainer.enable_progress_bar=false", "render.progress=false",
                             *overrides,
                             *((f"resume={resume / LAST_CKPT}",) if resume else ())], out)
    if resume is not None:
        return resume, wall
    (run,) = set(out.glob(f"*/{stage}/*")) - before
    return run, wall


def scene_dataset(preset: str, overrides: list[str]) -> str:
    """The name of the dataset folder (in :func:`output_dir`'s cache) that ``nrt-train
    preset=<preset> <overrides>`` trains on."""
    scene = compose_train([f"preset={preset}", *overrides]).scene
    return dataset_name(OmegaConf.to_container(scene, resolve=True), output_dir() / "datasets")


def ea_runs(scene: str, dataset: str | None = None) -> list[Path]:
    """The EA runs of ``scene`` under :func:`output_dir` that saved a checkpoint (those
    trained on the dataset folder named ``dataset``, when given), newest checkpoint first."""
    runs = [p.parent.parent for p in (output_dir() / scene / "ea").glob(f"*/{LAST_CKPT}")]
    runs = [r for r in runs if dataset is None or run_dataset(r) == dataset]
    return sorted(runs, key=lambda r: (r / LAST_CKPT).stat().st_mtime, reverse=True)


def finished(run: Path) -> bool:
    """Whether a run folder's training ran to its end (``run.json``'s ``finished_step``)."""
    return read_run_info(run).get("finished_step") is not None


def unfinished_run_error(run: Path) -> str | None:
    """Why ``run`` is no finished training run to read results from (no ``run.json``, or
    one without ``finished_step``: a killed run), with the fix; None when it is one."""
    if not (run / "run.json").exists():
        return f"{run} holds no run.json; give the folder of a finished training run."
    if not finished(run):
        return (f"the run in {run} did not reach its end (its run.json has no "
                "finished_step); continue it with the nrt-train overrides of its "
                f".hydra/overrides.yaml and resume={run / LAST_CKPT}, then read it again.")
    return None


def newest_checkpoint(scene: str, dataset: str | None = None) -> Path | None:
    """The last checkpoint of the newest finished EA run of ``scene`` under
    :func:`output_dir` (among those trained on the dataset folder named ``dataset``, when
    given); a run killed before its end is no start."""
    run = next((r for r in ea_runs(scene, dataset) if finished(r)), None)
    return (run / LAST_CKPT).resolve() if run is not None else None


def ea_checkpoint(name: str, preset: str, overrides: list[str] | None = None,
                  ea_steps: int | None = None) -> Path:
    """The EA checkpoint of the scene named ``name`` (its EA runs under :func:`output_dir`):
    the newest finished one trained on the photos of ``preset`` and ``overrides`` (default:
    the benchmark scene ``name``'s, :data:`SCENES`; another photo seed needs its own name);
    else the newest killed one resumed to its end; else a new stage-1 run's on them (of
    ``ea_steps`` steps; None: the preset's)."""
    overrides = list(SCENES[name] if overrides is None else overrides)
    dataset = scene_dataset(preset, overrides)
    found = newest_checkpoint(name, dataset)
    if found is not None:
        return found
    steps = [] if ea_steps is None else [f"budget.ea.steps={int(ea_steps)}"]
    killed = ea_runs(name, dataset)
    run = train("ea", output_dir(), preset, [*overrides, *steps],
                resume=killed[0] if killed else None)[0]
    return (run / LAST_CKPT).resolve()


def trains_as(run: Path, cfg: DictConfig) -> bool:
    """Whether a run's saved config (``.hydra/config.yaml``) trains what ``cfg`` does: the
    same :data:`TRAINING` sections once resolved, however their overrides were spelled."""
    saved = OmegaConf.load(run / ".hydra" / "config.yaml")

    def resolved(config: DictConfig, key: str):
        node = config[key]
        return OmegaConf.to_container(node, resolve=True) if isinstance(node, DictConfig) \
            else node

    return all(resolved(saved, k) == resolved(cfg, k) for k in TRAINING)


def run_like(stage: str, preset: str, overrides: list[str],
             logger: str = "[tensorboard,csv]") -> Path:
    """The newest finished run under :func:`output_dir` that trains what ``nrt-train
    stage=<stage> preset=<preset> <overrides>`` does (:func:`trains_as`); where there is
    none, that run, trained now through the CLI."""
    cfg = compose_train([f"stage={stage}", f"preset={preset}",
                         f"paths.data_dir={output_dir() / 'datasets'}", *overrides])
    runs = [p.parent.parent for p in (output_dir() / cfg.scene.name / stage).glob(
        f"*/{LAST_CKPT}")]
    runs = [r for r in runs if finished(r) and (r / ".hydra" / "config.yaml").exists()
            and trains_as(r, cfg)]
    if not runs:
        return train(stage, output_dir(), preset, overrides, logger=logger)[0]
    return max(runs, key=lambda r: (r / LAST_CKPT).stat().st_mtime)


def run_finals(run: Path, keep: dict[str, str]) -> dict:
    """A finished run's steps, training seconds and the final metrics ``keep`` (column ->
    metric key; a metric the run did not log is left out), from its ``run.json``."""
    info = read_run_info(run)
    final = info["final_metrics"]
    return {"steps": info["finished_step"], "train_s": round(final["time/wall_s"], 1),
            **{column: round(final[key], 4) for column, key in keep.items() if key in final}}


def commit_of(code: Path) -> str:
    """``code``'s git commit, ``+ changes`` when its work tree differs from it."""
    def git(*argv: str) -> str:
        return subprocess.run(["git", "-C", str(code), *argv], capture_output=True,
                              text=True).stdout.strip()
    head = git("rev-parse", "--short", "HEAD") or str(code)
    return head + (" + changes" if git("status", "--porcelain", "--untracked-files=no") else "")


def read_table(table: Path) -> list[dict]:
    """The rows of a benchmark's CSV table ([] where there is none yet)."""
    if not table.is_file():
        return []
    with open(table, newline="") as f:
        return list(csv.DictReader(f))


def append_rows(table: Path, fields: tuple[str, ...], rows: list[dict]) -> None:
    """Append ``rows`` to a benchmark's CSV table of columns ``fields``, written with its
    header where it is new (a killed benchmark keeps every row appended before)."""
    new = not table.is_file()
    table.parent.mkdir(parents=True, exist_ok=True)
    with open(table, "a", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=fields)
        if new:
            writer.writeheader()
        writer.writerows(rows)


def metric_rows(run: Path) -> list[dict]:
    """The rows of a run's CSV log: ``csv/metrics.csv``, then the log of each time it was
    resumed (``csv/resumed-<time>/metrics.csv``, oldest first), each log replacing the rows
    of the steps it logged again (those after the checkpoint it resumed from)."""
    rows: list[dict] = []
    for log in [run / "csv" / "metrics.csv",
                *sorted((run / "csv").glob(f"{RESUMED_PREFIX}*/metrics.csv"))]:
        with open(log) as f:
            part = list(csv.DictReader(f))
        steps = [int(r["step"]) for r in part if r.get("step")]
        if steps:
            rows = [r for r in rows if not r.get("step") or int(r["step"]) < min(steps)]
        rows += part
    return rows


def validation_rows(run: Path) -> list[dict[str, float]]:
    """A run's validation records in step order, each {metric: value} with its ``step`` and
    the training seconds then (``time/wall_s``): from ``csv/metrics.csv``, else from the
    TensorBoard event files."""
    if (run / "csv" / "metrics.csv").exists():
        rows = [{k: float(v) for k, v in r.items() if v not in ("", None)}
                for r in metric_rows(run)]
        return [r for r in rows if "val/mse_sigma_t_x100" in r]
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator
    events = EventAccumulator(str(run / "tensorboard"), size_guidance={"scalars": 0})
    events.Reload()
    by_step: dict[int, dict[str, float]] = {}
    scalars = events.Tags()["scalars"]
    for tag in (t for t in scalars if t.startswith("val/")):
        for event in events.Scalars(tag):
            by_step.setdefault(event.step, {"step": float(event.step)})[tag] = event.value
    for event in events.Scalars("time/wall_s") if "time/wall_s" in scalars else ():
        if event.step in by_step:
            by_step[event.step]["time/wall_s"] = event.value
    return [by_step[s] for s in sorted(by_step) if "val/mse_sigma_t_x100" in by_step[s]]


def series(run: Path, key: str) -> list[float]:
    """Every logged value of metric ``key`` of a run, in order."""
    return [float(r[key]) for r in metric_rows(run) if r.get(key)]
