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
from omegaconf import DictConfig, OmegaConf

from nrt.data.grids import MEDIUM_GRIDS_FILE, load_property_grids
from nrt.errors import NrtError
from nrt.run_dirs import LAST_CKPT, RUN_FILE
from nrt.stages.checkpoints import load_stage

if TYPE_CHECKING:
    from nrt.evaluation.sample import LatentMediumModel
    from nrt.stages.stage import Stage

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


EVAL_HINT = "(or grids=<file.npz> with scene=<name> to evaluate a property-grid file)"


def read_run_folder(path: str | Path, hint: str = EVAL_HINT) -> tuple[Path, dict, DictConfig]:
    """A run folder of ``nrt-train``: its path, ``run.json`` and composed config. Errors
    name what is missing and the fix; ``hint`` ends them (the command's alternative)."""
    path = Path(path).expanduser()
    if not path.is_dir():
        raise NrtError(f"run='{path}' does not exist (or is not a folder). Pass a run folder "
                       f"of nrt-train such as outputs/<scene>/<stage>/<timestamp>-<pid> {hint}.")
    info_file, cfg_file = path / RUN_FILE, path / ".hydra" / "config.yaml"
    if not info_file.is_file() or not cfg_file.is_file():
        raise NrtError(f"run='{path}' is not a run folder of nrt-train: it needs {RUN_FILE} "
                       "and .hydra/config.yaml. Pass a folder such as "
                       f"outputs/<scene>/<stage>/<timestamp>-<pid> {hint}.")
    return path, json.loads(info_file.read_text()), OmegaConf.load(cfg_file)


def open_run(path: str | Path) -> TrainedRun:
    """Read a run folder of ``nrt-train``; errors name what is missing and the fix."""
    path, info, cfg = read_run_folder(path)
    if "family_dir" in info:
        raise NrtError(f"run='{path}' is a generative run over the scene family "
                       f"'{info['family_dir']}' (mode=generative), which nrt-eval does not "
                       "evaluate; nrt-sample run=<it> scores a generative stage-2 run "
                       "(reconstructions, samples, FID). Its per-member grids are in "
                       "members/<name>/ and its codes in latents.npz.")
    effects = OmegaConf.to_container(cfg.scene.effects, resolve=True)
    return TrainedRun(path, info["stage"], info["scene"], Path(info["dataset_dir"]),
                      list(info["environments"]), effects,
                      str(cfg.model._target_))


def stage_class(run_dir: Path, target: str) -> type:
    """The stage class a run's config names (``model._target_``); a name this nrt does not
    have (a run of an earlier nrt) is refused naming the run."""
    from hydra.utils import get_class

    try:
        return get_class(target)
    except ImportError as error:
        raise NrtError(f"run='{run_dir}' was trained with the stage {target}, which this nrt "
                       "does not have (a run of an earlier nrt, whose checkpoints this nrt does "
                       "not read). Evaluate its exported grids instead (grids=<run>/"
                       f"{MEDIUM_GRIDS_FILE} scene=<name>), or train it again.") from error


def checkpoint_path(run: TrainedRun | Path, checkpoint: str) -> Path:
    """``last`` | ``best`` | a path -> the checkpoint file of ``run`` (or its folder)."""
    folder = run if isinstance(run, Path) else run.path
    ckpt = {"last": folder / LAST_CKPT,
            "best": folder / "checkpoints" / "best.ckpt"}.get(checkpoint, Path(checkpoint))
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
    ckpt = checkpoint_path(run, checkpoint)
    module: Stage = load_stage(stage_class(run.path, run.model_target), ckpt)
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


GENERATIVE_RTE = ("nrt-train stage=rte mode=generative scene=family "
                  "init.ea_ckpt=<generative EA run>/checkpoints/last.ckpt")
"""The command that trains what nrt-sample reads (its errors quote it)."""


@dataclass
class GenerativeRun:
    """A generative stage-2 run folder: its family folder, scene effects, model class and
    scene config (``scene``, with its ``family``)."""

    path: Path
    family_dir: Path
    effects: dict
    model_target: str
    scene: dict


def open_generative_run(path: str | Path) -> GenerativeRun:
    """Read a run folder of ``nrt-train stage=rte mode=generative``; a single-scene run or
    a generative run of another stage is refused with the command that trains one."""
    path, info, cfg = read_run_folder(path, hint=f"trained with `{GENERATIVE_RTE}`")
    stage = info.get("stage")
    if info.get("mode") != "generative" or "family_dir" not in info:
        raise NrtError(f"run='{path}' is a single-scene run (stage {stage}, scene "
                       f"{info.get('scene')}): nrt-sample needs a generative stage-2 run over "
                       f"a scene family, trained with `{GENERATIVE_RTE}` after `nrt-train "
                       "stage=ea mode=generative scene=family`.")
    if stage != "rte":
        ea_hint = (f"init.ea_ckpt={path / LAST_CKPT}" if stage == "ea"
                   else "init.ea_ckpt=<generative EA run>/checkpoints/last.ckpt")
        raise NrtError(f"run='{path}' is a generative {stage} run: it learned codes and EA "
                       "densities, no media to sample. nrt-sample needs a generative stage-2 "
                       f"run: `nrt-train stage=rte mode=generative scene=family {ea_hint}`, "
                       "then nrt-sample run=<that run>.")
    effects = OmegaConf.to_container(cfg.scene.effects, resolve=True)
    return GenerativeRun(path, Path(info["family_dir"]), effects,
                         str(cfg.model._target_),
                         OmegaConf.to_container(cfg.scene, resolve=True))


def load_generative_model(run: GenerativeRun, checkpoint: str = "last") -> LatentMediumModel:
    """The scene family of the run's stage (its ``scenes``, :mod:`nrt.stages.family`) from
    ``checkpoint``, on the CPU in eval mode, checked to decode codes (``codes``,
    ``member_names``, ``property_grids_for``, ``member_property_grids``)."""
    ckpt = checkpoint_path(run.path, checkpoint)
    module = load_stage(stage_class(run.path, run.model_target), ckpt)
    family = getattr(module, "scenes", None)
    if not all(hasattr(family, a) for a in ("codes", "member_names", "property_grids_for",
                                            "member_property_grids", "medium_bbox")):
        raise NrtError(f"run='{run.path}': its module {run.model_target} has no latent codes "
                       f"and decoder; nrt-sample needs a generative stage-2 run "
                       f"(`{GENERATIVE_RTE}`).")
    module.eval()
    return family
