"""One method trained for a fixed number of training seconds from one EA checkpoint, its
curves and nrt-eval's scores recorded as small files: the unit of every equal-time
comparison (``benchmarks.fair_comparison``, ``benchmarks.paper_tables``).

A record is two files beside each other: ``<name>.csv`` (property MSE x100 against
training seconds, measured every ``every_s`` seconds with the clock paused) and
``<name>.json`` (nrt-eval's metrics of the end: the Mitsuba re-render of the held-out
views under the held-back sky at the dataset's spp, LPIPS on, the noise floor beside; the
steps and seconds; the EA checkpoint it started from, by path and the SHA-256 of its
weights; the machine's speed just before and just after training
(:func:`~benchmarks.machine_probe.machine_speed`), so records made hours apart can be
checked for a change of speed; the callers' tags, among them ``code``: the commit whose
configs hold the method's defaults). A record whose JSON exists is not run again, so a
killed benchmark resumes where it stopped.
"""

from __future__ import annotations

import csv
import hashlib
import json
import math
import time
from pathlib import Path

import numpy as np
import torch

from benchmarks.common import metric_rows, run_cli, train
from benchmarks.machine_probe import machine_speed

PROPERTIES = ("sigma_a", "sigma_s", "sigma_t", "g")
EVAL_KEYS = ("psnr_novel", "ssim_novel", "lpips_novel", "psnr_noise_floor_novel")
MANY_STEPS = 1_000_000  # the budget stops the run
HELD_BACK_SKY = 2
"""The sky no method trains on (the paper's formulation trains on sky 0 alone, the others on
skies 0 and 1): every method's novel-illumination score is its re-render under this one."""


def write_curve(run: Path, path: Path) -> int:
    """The run's property MSEs x100 against training seconds as CSV; the number of points."""
    rows = [r for r in metric_rows(run) if r.get("val/mse_sigma_t_x100") and
            r.get("time/wall_s")]
    with open(path, "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(["wall_s", *PROPERTIES])
        for r in rows:
            w.writerow([f"{float(r['time/wall_s']):.2f}",
                        *(f"{float(r[f'val/mse_{k}_x100']):.5g}" if r.get(f"val/mse_{k}_x100")
                          else "" for k in PROPERTIES)])
    return len(rows)


def evaluate(run: Path, out: Path) -> dict:
    """nrt-eval's metrics of a run: the Mitsuba re-render of the held-out views under
    :data:`HELD_BACK_SKY` at the dataset's spp (every method alike), with LPIPS and the
    noise floor."""
    run_cli("eval", [f"run={run}", f"rerender.environments=[{HELD_BACK_SKY}]",
                     "relight.enabled=false", "export.mitsuba=false", "render.progress=false"],
            out)
    latest = sorted(run.glob("eval/*/metrics.json"))[-1]
    return json.loads(latest.read_text())["metrics"]


def weights_sha256(ckpt: Path) -> str:
    """The SHA-256 (hex) of a Lightning checkpoint's weights: every tensor of its
    ``state_dict`` with its name, in name order. Two checkpoints with the same weights agree
    whatever else their files hold (times, loop counters)."""
    state = torch.load(ckpt, map_location="cpu", weights_only=False)["state_dict"]
    digest = hashlib.sha256()
    for name in sorted(state):
        digest.update(name.encode())
        digest.update(state[name].detach().contiguous().view(-1).view(torch.uint8).numpy()
                      .tobytes())
    return digest.hexdigest()


def run_method(path: Path, stage_overrides: list[str], scene_overrides: list[str], ckpt: Path,
               budget_s: float, every_s: float, preset: str, out: Path, tags: dict) -> dict:
    """Train ``stage_overrides`` (``stage=...`` first) on the scene of ``scene_overrides``
    from ``ckpt`` for ``budget_s`` training seconds, evaluate it and write the record
    ``path`` (.csv and .json; ``tags`` go into the JSON as they are); the record, with the
    run folder under ``run``."""
    stage = stage_overrides[0].split("=")[1]
    start = time.perf_counter()
    before = machine_speed()
    run, _ = train(stage, out, preset, [
        *stage_overrides[1:], *scene_overrides, f"init.ea_ckpt={ckpt}", f"budget_s={budget_s}",
        f"budget.{stage}.steps={MANY_STEPS}", f"callbacks.property_metrics.every_s={every_s}"])
    after = machine_speed()
    path.parent.mkdir(parents=True, exist_ok=True)
    points = write_curve(run, path.with_suffix(".csv"))
    metrics = evaluate(run, out)
    info = json.loads((run / "run.json").read_text())
    steps = max(int(float(r["step"])) for r in metric_rows(run) if r.get("step"))
    record = {**tags, "budget_s": budget_s, "preset": preset,
              "seconds": info["final_metrics"]["time/wall_s"], "steps": steps + 1,
              "curve_points": points, "learns_g": "mse_g_x100" in metrics,
              "ea_ckpt": {"path": str(ckpt), "weights_sha256": weights_sha256(ckpt)},
              "machine": {"before": before, "after": after},
              "wall_s_with_eval": round(time.perf_counter() - start, 1),
              "metrics": {k: v for k, v in metrics.items()
                          if k.startswith(("mse_", *EVAL_KEYS))}}
    path.with_suffix(".json").write_text(json.dumps(record, indent=1) + "\n")
    return {**record, "run": str(run)}


def read_record(path: Path) -> dict:
    """A record (``path``: its .json) with its curve as arrays under ``curve``."""
    record = json.loads(path.with_suffix(".json").read_text())
    with open(path.with_suffix(".csv"), newline="") as f:
        rows = list(csv.DictReader(f))
    record["curve"] = {k: np.array([float(r[k]) if r[k] else math.nan for r in rows])
                       for k in ("wall_s", *PROPERTIES)}
    return record


def summary_line(name: str, record: dict) -> str:
    """One progress line of a finished record."""
    m = record["metrics"]
    return (f"{name}: sigma_t {m['mse_sigma_t_x100']:.3f} sigma_s {m['mse_sigma_s_x100']:.3f} "
            f"PSNR {m.get('psnr_novel', math.nan):.2f} ({record['curve_points']} curve points, "
            f"{record['steps']} steps) {record.get('run', '')}")
