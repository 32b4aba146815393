"""A finished ``nrt-train`` run as ``nrt-eval`` sees it: its stage, dataset, training
environments and learned medium.

``nrt-train`` writes ``run.json`` into every run folder (stage, scene, dataset folder,
environments trained on, exports); the composed config is in ``.hydra/config.yaml``.
"""

from __future__ import annotations

import json
import logging
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import torch
from omegaconf import OmegaConf

from nrt.data.grids import MEDIUM_GRIDS_FILE, load_property_grids
from nrt.errors import NrtError
from nrt.modules.stages.components import current_target
from nrt.run_dirs import LAST_CKPT, RUN_FILE

if TYPE_CHECKING:
    from nrt.modules.stages.stage import Stage

log = logging.getLogger(__name__)


@dataclass
class TrainedRun:
    path: Path
    stage: str
    scene: str
    dataset_dir: Path
    trained_envs: list[str]
    effects: dict
    model_target: str


def open_run(path: str | Path) -> TrainedRun:
    """Read a run folder of ``nrt-train``; errors name what is missing and the fix."""
    path = Path(path).expanduser()
    if not path.is_dir():
        raise NrtError(f"run='{path}' does not exist (or is not a folder). Pass a run folder "
                       "of nrt-train such as outputs/<scene>/<stage>/<timestamp>-<pid> (or "
                       "grids=<file.npz> with scene=<name> to evaluate a property-grid file).")
    info_file, cfg_file = path / RUN_FILE, path / ".hydra" / "config.yaml"
    if not info_file.is_file() or not cfg_file.is_file():
        raise NrtError(f"run='{path}' is not a run folder of nrt-train: it needs {RUN_FILE} "
                       "and .hydra/config.yaml. Pass a folder such as "
                       "outputs/<scene>/<stage>/<timestamp>-<pid> (or grids=<file.npz> with "
                       "scene=<name> to evaluate a property-grid file).")
    info = json.loads(info_file.read_text())
    if "family_dir" in info:
        raise NrtError(f"run='{path}' is a generative run over the scene family "
                       f"'{info['family_dir']}' (mode=generative), which nrt-eval does not "
                       "evaluate yet; its per-member density grids are in "
                       "members/<name>/density_grid.npz and its codes in latents.npz.")
    cfg = OmegaConf.load(cfg_file)
    effects = OmegaConf.to_container(cfg.scene.effects, resolve=True)
    return TrainedRun(path, info["stage"], info["scene"], Path(info["dataset_dir"]),
                      list(info["environments"]), effects,
                      current_target(str(cfg.model._target_)))


def checkpoint_path(run: TrainedRun, checkpoint: str) -> Path:
    """``last`` | ``best`` | a path -> the checkpoint file."""
    ckpt = {"last": run.path / LAST_CKPT,
            "best": run.path / "checkpoints" / "best.ckpt"}.get(checkpoint, Path(checkpoint))
    if not ckpt.is_file():
        raise NrtError(f"checkpoint={checkpoint}: no checkpoint at '{ckpt}'. Use last, best or "
                       "a path to a .ckpt of this run.")
    return ckpt


def run_grids(run: TrainedRun, resolution: int | None, checkpoint: str = "last"
              ) -> tuple[dict[str, torch.Tensor], str]:
    """The run's medium as property grids, and where they came from: its exported
    ``medium_grids.npz`` when ``resolution`` is None (or matches), else the model of
    ``checkpoint`` queried at ``resolution`` cells per axis."""
    exported = run.path / MEDIUM_GRIDS_FILE
    if exported.is_file() and checkpoint == "last":
        grids = load_property_grids(exported)
        if resolution is None or grids["g"].shape[0] == resolution:
            return grids, str(exported)
    if resolution is None:
        resolution = 64
    from hydra.utils import get_class

    ckpt = checkpoint_path(run, checkpoint)
    module: Stage = get_class(run.model_target).load_from_checkpoint(ckpt, map_location="cpu")
    grids = module.property_grids(int(resolution))
    if grids is None:
        raise NrtError(f"run='{run.path}' (stage {run.stage}) has no learned medium to "
                       "evaluate: stages rte and dpt learn one; ea learns a density only and "
                       "forward solves for light in the true medium.")
    bbox = module.medium_bbox()
    out = {k: v.detach().float().cpu() for k, v in grids.items()}
    if bbox is not None:
        out["bbox"] = bbox.detach().float().cpu()
    return out, f"{ckpt} at {resolution}^3"
