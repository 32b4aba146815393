"""The paper preset on one GPU in about 8 minutes, with nothing to download; or, with
``--cpu-memory``, whether the paper preset's stage 2 fits in 80 GB.

GPU: renders a reduced ``paper`` dataset with ``cuda_ad_rgb`` (the preset's 256 x 256
photos, 128^3 medium and skies; fewer views and samples per pixel), trains stage 1 and
stage 2 a fixed number of steps at the paper preset, the baseline (``stage=dpt``) as many
as stage 2, each under a cap of ``--cap-s`` training seconds (reported where it binds),
and runs ``nrt-eval`` of stage 2 (Mitsuba re-render of two held-out views under the novel
sky; no LPIPS, no relighting). Prints per stage: steps, training seconds and seconds per
step, the peak GPU memory its training process allocated (``torch.cuda.max_memory_allocated``)
and its peak resident memory, both logged into the run's CSV by
:class:`nrt.callbacks.PeakMemory`, and the property MSE x100 at the start and the end;
then the evaluation's PSNR and the wall time of the whole smoke run.

``--cpu-memory`` (no GPU needed): a reduced paper dataset (``llvm_ad_rgb``, few views),
2 stage-1 steps, then ``--steps`` stage-2 steps at the paper preset on the CPU, logging
every step; prints the peak resident memory after each step (``resource.getrusage``, the
same callback), and that peak plus the memory of the full preset's photos against 80 GB.
RSS on the CPU stands for the GPU's memory only roughly: it also holds Python, torch and
Mitsuba, and the CUDA allocator caches blocks.

    python -m benchmarks.gpu_smoke [--views 40] [--spp 64] [--steps 300] [--rte-steps 100]
        [--cap-s 150] [--output DIR]
    python -m benchmarks.gpu_smoke --cpu-memory [--steps 3] [--output DIR]
"""

from __future__ import annotations

import argparse
import json
import tempfile
import time
from pathlib import Path

from benchmarks.common import compose_train, metric_rows, output_dir, run_cli, series, train
from nrt.run_dirs import LAST_CKPT

PEAK = "+callbacks.peak_memory={_target_:nrt.callbacks.PeakMemory}"
"""Logs ``memory/peak_rss_gib`` and, on a GPU, ``memory/peak_cuda_gib`` each step."""
PROPERTIES = ("sigma_a", "sigma_s", "sigma_t", "g")
GIB = 2**30
LIMIT_GB = 80


def views(args) -> list[str]:
    """The overrides that reduce the paper preset's photos."""
    return [f"scene.cameras.num_train={args.views}", f"scene.cameras.num_test={args.test_views}",
            f"scene.spp={args.spp}"]


def reduced(args, variant: str) -> list[str]:
    """The overrides of the reduced paper dataset (and of every run on it)."""
    return [*views(args), f"render.variant={variant}",
            f"paths.data_dir={output_dir() / 'datasets'}"]


def last(run: Path, key: str) -> float:
    values = series(run, key)
    return values[-1] if values else float("nan")


def stage_row(label: str, run: Path, cap_s: float | None) -> str:
    """One Markdown row of a finished run: steps, training seconds, seconds per step, peak
    GPU and resident memory (GiB), property MSE x100 start -> end."""
    info = json.loads((run / "run.json").read_text())
    seconds = info["final_metrics"].get("time/wall_s", float("nan"))
    steps = info.get("finished_step") or 0
    capped = " (capped)" if cap_s is not None and seconds >= cap_s else ""
    cuda = max(series(run, "memory/peak_cuda_gib"), default=float("nan"))
    rss = max(series(run, "memory/peak_rss_gib"), default=float("nan"))
    mse = " | ".join(f"{series(run, f'val/mse_{k}_x100')[0]:.3f} -> "
                     f"{last(run, f'val/mse_{k}_x100'):.3f}"
                     if series(run, f"val/mse_{k}_x100") else "-" for k in PROPERTIES)
    per_step = seconds / steps if steps else float("nan")
    return (f"| {label} | {steps}{capped} | {seconds:.1f} | {per_step:.3f} | {cuda:.2f} | "
            f"{rss:.2f} | {mse} |")


def gpu_smoke(args, out: Path) -> None:
    data = reduced(args, "cuda_ad_rgb")
    common = [*data, "trainer=gpu", PEAK, "trainer.log_every_n_steps=1", "budget.val_views=2"]
    start = time.perf_counter()
    render_s = run_cli("data", ["preset=paper", *data, "render.progress=false"], out)
    runs = {}
    stages = (("ea", args.steps), ("rte", args.rte_steps), ("dpt", args.rte_steps))
    for stage, steps in stages:
        start_from = [f"init.ea_ckpt={runs['ea'] / LAST_CKPT}"] if stage != "ea" else []
        runs[stage] = train(stage, out, "paper", [
            *common, *start_from, f"budget.{stage}.steps={steps}", f"budget_s={args.cap_s}",
            f"budget.val_every={steps}", f"budget.checkpoint_every={steps}"], logger="csv")[0]
    eval_s = run_cli("eval", [f"run={runs['rte']}", "preset=paper", "metrics.lpips=false",
                              "relight.enabled=false", "rerender.max_views=2",
                              "rerender.noise_floor=false"], out)
    metrics = json.loads(sorted(runs["rte"].glob("eval/*/metrics.json"))[-1].read_text())
    total = time.perf_counter() - start
    print(f"\nGPU smoke run of the paper preset ({args.views} + {args.test_views} views a sky, "
          f"{args.spp} spp): render {render_s:.0f} s, evaluation {eval_s:.0f} s, "
          f"all {total:.0f} s{' (over 8 minutes)' if total > 480 else ''}; runs under {out}\n")
    print("| stage | steps | train s | s/step | peak GPU GiB | peak RSS GiB | "
          + " | ".join(f"{k} MSE x100" for k in PROPERTIES) + " |")
    print("| --- " * (6 + len(PROPERTIES)) + "|")
    for stage, _ in stages:
        print(stage_row(stage, runs[stage], args.cap_s))
    psnr = {k: round(v, 2) for k, v in metrics["metrics"].items() if k.startswith("psnr_")}
    print(f"\nnrt-eval of stage 2: {psnr}")


def photo_bytes(overrides: list[str]) -> int:
    """Bytes of the photos a stage-2 run holds (its training skies' train and test views,
    float32 RGB) for the paper preset with ``overrides``."""
    scene = compose_train(["preset=paper", "stage=rte", *overrides]).scene
    cams, skies = scene.cameras, len(scene.environments.train)
    return (cams.num_train + cams.num_test) * skies * cams.width * cams.height * 3 * 4


def cpu_memory(args, out: Path) -> None:
    data = reduced(args, "auto")
    common = [*data, "trainer=cpu", PEAK, "trainer.log_every_n_steps=1",
              "budget.val_every=100000", "budget.checkpoint_every=100000"]
    run_cli("data", ["preset=paper", *data, "render.progress=false"], out)
    ea = train("ea", out, "paper", [*common, "budget.ea.steps=2"], logger="csv")[0]
    rte = train("rte", out, "paper", [*common, f"budget.rte.steps={args.steps}",
                                      f"init.ea_ckpt={ea / LAST_CKPT}"], logger="csv")[0]
    rss = [(int(float(r["step"])), float(r["memory/peak_rss_gib"]))
           for r in metric_rows(rte) if r.get("memory/peak_rss_gib")]
    print(f"\nStage 2 at the paper preset on the CPU ({args.views} + {args.test_views} views "
          f"a sky, {args.steps} steps); runs under {out}\n")
    print("| step | peak RSS GiB |\n| ---: | ---: |")
    for step, value in rss:
        print(f"| {step} | {value:.2f} |")
    photos = (photo_bytes([]) - photo_bytes(views(args))) / GIB
    peak = max((value for _, value in rss), default=float("nan"))
    total = peak + photos
    print(f"\npeak {peak:.2f} GiB + {photos:.2f} GiB for the full preset's photos = "
          f"{total:.2f} GiB ({total * GIB / 1e9:.1f} GB): "
          f"{'fits' if total * GIB <= LIMIT_GB * 1e9 else 'does not fit'} in {LIMIT_GB} GB")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--cpu-memory", action="store_true",
                        help="stage 2's peak memory on the CPU instead of the GPU smoke run")
    parser.add_argument("--views", type=int, default=None,
                        help="training views a sky (default 40; --cpu-memory: 4)")
    parser.add_argument("--test-views", type=int, default=None,
                        help="held-out views a sky (default 4; --cpu-memory: 2)")
    parser.add_argument("--spp", type=int, default=None,
                        help="samples per pixel of the photos (default 64; --cpu-memory: 4)")
    parser.add_argument("--steps", type=int, default=None,
                        help="stage-1 steps (default 300); --cpu-memory: stage-2 steps (3)")
    parser.add_argument("--rte-steps", type=int, default=100,
                        help="stage-2 and baseline steps")
    parser.add_argument("--cap-s", type=float, default=150.0,
                        help="training seconds at most per stage")
    parser.add_argument("--output", help="folder for the runs (default: a temporary one)")
    args = parser.parse_args()
    small = args.cpu_memory
    args.views = args.views or (4 if small else 40)
    args.test_views = args.test_views or (2 if small else 4)
    args.spp = args.spp or (4 if small else 64)
    args.steps = args.steps or (3 if small else 300)
    out = Path(args.output or tempfile.mkdtemp(prefix="nrt_gpu_smoke_"))
    if small:
        cpu_memory(args, out)
        return
    import torch

    if not torch.cuda.is_available():
        parser.error("no CUDA device: the smoke run needs a GPU (--cpu-memory measures "
                     "stage 2's memory on the CPU).")
    gpu_smoke(args, out)


if __name__ == "__main__":
    main()
