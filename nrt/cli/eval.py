"""``nrt-eval``: evaluate a trained medium (a run of nrt-train, or a property-grid file).

Writes into a new folder (``<run>/eval/<timestamp>-<pid>``): ``metrics.json`` and
``metrics.md`` (property MSEs, re-render PSNR/SSIM/LPIPS under novel illumination, the
Monte Carlo noise floor, relighting), ``report.png`` (slices of the medium beside the truth,
re-renders beside the photos, the metrics; :mod:`nrt.evaluation.report_figure`),
``previews/*.png`` (truth | ours | error),
``relight/*.exr|png``, the exported ``medium_grids.npz`` and Mitsuba ``volumes/``, and
the same metrics and pictures to ``tensorboard/``. See :mod:`nrt.evaluation.evaluate`.
"""

from __future__ import annotations

import json
import logging
from pathlib import Path

from hydra.core.hydra_config import HydraConfig
from omegaconf import DictConfig, OmegaConf

from nrt.cli.common import run_app
from nrt.errors import NrtError

log = logging.getLogger(__name__)


def check_inputs(cfg: DictConfig) -> dict:
    """What to evaluate, checked cheaply before any metric network or render is set up:
    the run folder (or the grid file and the scene's keys)."""
    from nrt.evaluation.runs import open_run

    if cfg.run and cfg.grids:
        raise NrtError("Give either run=<run folder> or grids=<file.npz>, not both.")
    if cfg.run:
        return {"run": open_run(cfg.run)}
    if cfg.grids:
        from nrt.data.spec import resolve_scene

        path = Path(str(cfg.grids)).expanduser()
        if not path.is_file():
            raise NrtError(f"grids='{path}' is not a file. Pass a property-grid .npz "
                           "(sigma_a, sigma_s, g; README \"Data format\").")
        scene = OmegaConf.to_container(cfg.scene, resolve=True)
        if not scene.get("path"):
            resolve_scene(scene)  # the scene's keys, before a dataset is rendered
        return {"grids": path, "scene": scene}
    raise NrtError("nrt-eval needs run=<run folder of nrt-train> (e.g. "
                   "outputs/default/rte/<timestamp>-<pid>) or grids=<property-grid .npz> "
                   "with scene=<name>.")


def load_medium(cfg: DictConfig, inputs: dict) -> dict:
    """The medium of :func:`check_inputs`: grids, effects, dataset folder (rendered when
    missing), trained environments (a grid file's are unknown: ``scene_train``, the
    scene's ``environments.train``, stands for them), source."""
    from nrt.data.grids import load_property_grids
    from nrt.data.render import ensure_dataset
    from nrt.evaluation.runs import run_grids

    if "run" in inputs:
        run = inputs["run"]
        grids, source = run_grids(run, cfg.export.resolution, str(cfg.checkpoint))
        return {"grids": grids, "effects": run.effects, "dataset_dir": run.dataset_dir,
                "trained": run.trained_envs, "source": source, "stage": run.stage}
    scene, path = inputs["scene"], inputs["grids"]
    dataset_dir = ensure_dataset(scene, cfg.paths.data_dir, variant=cfg.render.variant,
                                 progress=cfg.render.progress)
    return {"grids": load_property_grids(path), "effects": scene["effects"],
            "dataset_dir": dataset_dir, "trained": [], "source": str(path), "stage": "grids",
            "scene_train": scene["environments"].get("train", [0])}


def rows_table(rows: list[dict]) -> list[str]:
    """Rows of equal keys as the lines of a Markdown table (floats to 4 digits)."""
    keys = list(rows[0])
    return ["| " + " | ".join(keys) + " |", "|" + "---|" * len(keys)] + [
        "| " + " | ".join(f"{r[k]:.4g}" if isinstance(r[k], float) else str(r[k])
                          for k in keys) + " |" for r in rows]


def markdown(metrics: dict[str, float], frames: list[dict], title: str) -> str:
    """The metrics as Markdown tables: all values, then one row per re-rendered frame."""
    lines = [f"# {title}", "", "| metric | value |", "|---|---:|"]
    lines += [f"| {k} | {v:.6g} |" for k, v in sorted(metrics.items())]
    if frames:
        lines += ["", *rows_table(frames)]
    return "\n".join(lines) + "\n"


def eval_task(cfg: DictConfig) -> dict:
    import torch
    from torch.utils.tensorboard import SummaryWriter

    from nrt.data.dataset import load_dataset
    from nrt.data.grids import MEDIUM_GRIDS_FILE, resample_grids, save_property_grids
    from nrt.evaluation import evaluate
    from nrt.evaluation.images import save_png
    from nrt.evaluation.report_figure import write_evaluation_report
    from nrt.metrics import LPIPS
    from nrt.mitsuba.export import write_medium_files
    from nrt.mitsuba.variant import select_variant

    out_dir = Path(HydraConfig.get().runtime.output_dir)
    inputs = check_inputs(cfg)
    try:  # before any render: a missing network fails in seconds
        lpips = LPIPS(str(cfg.metrics.lpips_net)) if cfg.metrics.lpips else None
    except NrtError as exc:
        raise NrtError(f"{exc} Or skip LPIPS with metrics.lpips=false.") from None
    medium = load_medium(cfg, inputs)
    data = load_dataset(medium["dataset_dir"], "test")
    if not medium["trained"] and "scene_train" in medium:  # a grid file: the scene's skies
        medium["trained"] = evaluate.named_environments(data, medium["scene_train"])
    grids = medium["grids"]
    bbox = grids.get("bbox", data.bbox)
    if cfg.export.resolution and grids["g"].shape[0] != int(cfg.export.resolution):
        grids = resample_grids(grids, int(cfg.export.resolution))
    grids = {k: grids[k] for k in ("sigma_a", "sigma_s", "g")}
    save_property_grids(out_dir / MEDIUM_GRIDS_FILE, grids, bbox)
    if cfg.export.mitsuba:
        mi = select_variant(cfg.render.variant)
        write_medium_files(mi, out_dir / "volumes", grids, bbox, medium["effects"])
    result = evaluate.Evaluation()
    if data.ground_truth is not None:
        result.metrics.update(evaluate.property_metrics(grids, data.ground_truth,
                                                        medium["effects"]))
    evaluate.rerender_metrics(grids, medium["effects"], data, medium["trained"],
                              cfg.rerender, lpips, result)
    if cfg.relight.enabled:
        evaluate.relight(grids, medium["effects"], data, cfg.relight, out_dir, lpips, result)
    for name, panel in result.pictures.items():
        if not name.startswith("relit"):
            save_png(out_dir / "previews" / f"{name}.png", panel)
    report = {"source": medium["source"], "stage": medium["stage"],
              "dataset": str(medium["dataset_dir"]), "trained_environments": medium["trained"],
              "metrics": result.metrics, "frames": result.frames,
              "settings": OmegaConf.to_container(cfg, resolve=True)}
    (out_dir / "metrics.json").write_text(json.dumps(report, indent=1))
    (out_dir / "metrics.md").write_text(markdown(
        result.metrics, result.frames, f"nrt-eval of {medium['source']}"))
    figure = write_evaluation_report(
        out_dir / "report.png", grids, data.ground_truth, medium["effects"], result,
        medium["source"], (data.spec or {}).get("name", data.root.name), **cfg.report)
    with SummaryWriter(str(out_dir / "tensorboard")) as writer:
        for key, value in result.metrics.items():
            writer.add_scalar(f"eval/{key}", value, 0)
        writer.add_image("eval/report", figure, 0, dataformats="HWC")
        for name, panel in result.pictures.items():
            writer.add_image(f"eval/{name}", torch.as_tensor(panel).float(), 0,
                             dataformats="HWC")
    shown = {k: round(v, 4) for k, v in result.metrics.items()
             if k.startswith(("mse_", "psnr_", "ssim_", "lpips_"))}
    log.info("Evaluation of %s in %s: %s", medium["source"], out_dir, shown)
    return {"eval_dir": str(out_dir), "metrics": result.metrics}


def main() -> None:
    run_app(eval_task, "eval")


if __name__ == "__main__":
    main()
