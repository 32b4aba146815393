"""``nrt-train``: train one stage on a scene (rendering its dataset first when missing).

Short and linear, in the lightning-hydra-template manner: compose, seed, checks, model and
callbacks (so that what the config alone decides is refused before any rendering), data,
loggers, trainer, fit (resuming when asked), export. The EA checkpoint a stage starts
from is resolved to an absolute path and recorded in ``run.json`` and in the saved
``.hydra/config.yaml`` (``init.ea_ckpt``). Lightning, torch and
Mitsuba are imported inside the task, so ``--cfg``, ``--help`` and config errors answer
at once.
"""

from __future__ import annotations

import logging
from pathlib import Path

import hydra
from hydra.core.hydra_config import HydraConfig
from omegaconf import DictConfig, OmegaConf

from nrt.cli.common import run_app
from nrt.errors import NrtError
from nrt.run_dirs import (
    LAST_CKPT,
    latest_run_with_checkpoint,
    read_run_info,
    write_run_info,
)

log = logging.getLogger(__name__)


ZERO_ALLOWED = ("light_degree", "sky_env_directions", "sky_phase_directions")
"""Counts of ``budget`` for which 0 is meaningful (SH band 0 only; one of the two MIS
strategies left out); every other count must be at least 1."""

FRACTIONS = ("light_warmup",)
"""Shares of a run in ``budget``, in [0, 1)."""

RUN_COUNTS = ("stage.steps", "stage.rays_per_batch", "data.steps_per_epoch")
"""Counts outside ``budget`` that a user may override directly."""


def _leaves(node, key: str):
    """``(dotted key, value)`` of every leaf of a plain container; a list of numbers is
    one leaf."""
    if isinstance(node, dict):
        for name, child in node.items():
            yield from _leaves(child, f"{key}.{name}")
    else:
        yield key, node


def _is_count(value, least: int) -> bool:
    return isinstance(value, int) and not isinstance(value, bool) and value >= least


def _count_error(key: str, value, least: int) -> NrtError:
    return NrtError(f"{key}={value}: must be a whole number >= {least} (a count of steps, "
                    "rays, samples, cells or layers; for a list, each entry). Fix the "
                    "override, or leave the key to the preset (conf/preset/).")


def _is_number(value) -> bool:
    return isinstance(value, int | float) and not isinstance(value, bool)


def check_budget(cfg: DictConfig) -> None:
    """Refuse counts and shares that no run can use (``budget.ea.steps=-3``, a zero batch
    size, a negative resolution, ``budget_s=-5``) with the key in the message, before
    anything is built or loaded. Schedules (``*upsample_at``) are checked by their stage."""
    budget = OmegaConf.to_container(cfg.budget, resolve=True)
    for key, value in _leaves(budget, "budget"):
        name = key.rsplit(".", 1)[-1]
        if isinstance(value, bool) or name.endswith("upsample_at") or \
                (name == "val_views" and value is None):
            continue
        if name in FRACTIONS:
            if not _is_number(value) or not 0 <= value < 1:
                raise NrtError(f"{key}={value}: must be a share of the run in [0, 1).")
            continue
        least = 0 if name in ZERO_ALLOWED else 1
        items = value if isinstance(value, list) else [value]
        if not items or not all(_is_count(item, least) for item in items):
            raise _count_error(key, value, least)
    for key in RUN_COUNTS:
        if not _is_count(OmegaConf.select(cfg, key), 1):
            raise _count_error(key, OmegaConf.select(cfg, key), 1)
    if cfg.budget_s is not None and (not _is_number(cfg.budget_s) or cfg.budget_s <= 0):
        raise NrtError(f"budget_s={cfg.budget_s}: must be a positive number of seconds of "
                       "training (or null for no time limit).")


def resume_checkpoint(cfg: DictConfig, run_dir: Path) -> str | None:
    """Checkpoint to continue from: ``resume=true`` -> this run folder's last.ckpt (the
    run-dir resolver picked the latest run), ``resume=<path>`` -> that file."""
    if cfg.resume in (None, False):
        return None
    ckpt = run_dir / LAST_CKPT if cfg.resume is True else Path(str(cfg.resume))
    if not ckpt.is_file():
        raise NrtError(f"resume={cfg.resume}: no checkpoint at '{ckpt}'. resume=true continues "
                       f"the newest run of scene '{cfg.scene.name}', stage '{cfg.stage.name}' "
                       "that saved checkpoints/last.ckpt; pass resume=<path/to/file.ckpt> for "
                       "another, or drop resume to start afresh.")
    return str(ckpt)


def resolve_ea_checkpoint(cfg: DictConfig, recorded: str | None = None) -> str | None:
    """The EA checkpoint whose density stage 2 (and dpt) modulates, as an absolute path set
    into ``cfg.init.ea_ckpt``; None for stages that do not start from one.

    ``init.ea_ckpt`` when given; else ``recorded`` (the one a resumed run started from);
    else the newest EA run of the same scene that saved a checkpoint."""
    if OmegaConf.select(cfg, "model.density.source") != "ea":
        return None
    if cfg.init.ea_ckpt:
        path = Path(str(cfg.init.ea_ckpt)).expanduser()
        if not path.is_file():
            raise NrtError(f"init.ea_ckpt='{cfg.init.ea_ckpt}' is not a checkpoint file. Train "
                           f"stage 1 first (nrt-train stage=ea scene={cfg.scene.name}) and pass "
                           "its checkpoints/last.ckpt, or drop init.ea_ckpt to start from the "
                           "newest EA run of the scene (stage 2 also runs without a first "
                           "stage: init=none).")
    elif recorded and Path(recorded).is_file():
        path = Path(recorded)
    else:
        base = Path(cfg.paths.output_dir) / cfg.scene.name / "ea"
        run = latest_run_with_checkpoint(base)
        if run is None:
            raise NrtError(f"stage={cfg.stage.name} starts from the EA density of scene "
                           f"'{cfg.scene.name}', but no EA run under '{base}' saved "
                           f"{LAST_CKPT}. Run `nrt-train stage=ea scene={cfg.scene.name}` "
                           "first, pass init.ea_ckpt=<path/to/last.ckpt>, or use init=none for "
                           "the single-stage ablation.")
        path = run / LAST_CKPT
    cfg.init.ea_ckpt = str(path.resolve())
    log.info("Stage %s starts from EA checkpoint %s", cfg.stage.name, cfg.init.ea_ckpt)
    return cfg.init.ea_ckpt


def save_config(cfg: DictConfig, run_dir: Path) -> None:
    """Write ``cfg`` over the copy Hydra saved before the task ran (``.hydra/config.yaml``,
    or the resumed run's ``.hydra/<tag>/config.yaml``), so that it shows what the task
    resolved (the EA checkpoint)."""
    subdir = HydraConfig.get().output_subdir
    if subdir is not None:
        (run_dir / str(subdir) / "config.yaml").write_text(OmegaConf.to_yaml(cfg))


def train_task(cfg: DictConfig) -> dict:
    import lightning as L

    from nrt.data.render import ensure_dataset

    run_dir = Path(HydraConfig.get().runtime.output_dir)
    L.seed_everything(cfg.seed, workers=True)
    # What the config alone decides is refused before any rendering or data loading:
    # counts no run can use, a missing EA run or resume checkpoint, and the checks of the
    # model and callbacks themselves (e.g. stage 2 on truncated scattering orders).
    check_budget(cfg)
    ckpt = resume_checkpoint(cfg, run_dir)
    ea_ckpt = resolve_ea_checkpoint(cfg, read_run_info(run_dir).get("ea_ckpt") if ckpt else None)
    if ea_ckpt is not None:
        save_config(cfg, run_dir)
    model = hydra.utils.instantiate(cfg.model, _convert_="all")
    callbacks = [hydra.utils.instantiate(c) for c in cfg.callbacks.values()]
    dataset_dir = ensure_dataset(OmegaConf.to_container(cfg.scene, resolve=True),
                                 cfg.paths.data_dir, variant=cfg.render.variant,
                                 progress=cfg.render.progress)
    datamodule = hydra.utils.instantiate(cfg.data, dataset_dir=str(dataset_dir))
    datamodule.setup()
    write_run_info(run_dir, stage=cfg.stage.name, scene=cfg.scene.name,
                   dataset_dir=str(Path(dataset_dir).resolve()),
                   environments=datamodule.train_data.environments_used(),
                   **({"ea_ckpt": ea_ckpt} if ea_ckpt is not None else {}))
    loggers = [hydra.utils.instantiate(lg) for lg in cfg.logger.values()]
    trainer = hydra.utils.instantiate(cfg.trainer, callbacks=callbacks, logger=loggers)
    log.info("Run folder %s; dataset %s%s", run_dir, dataset_dir,
             f"; resuming from {ckpt}" if ckpt else "")
    trainer.fit(model, datamodule=datamodule, ckpt_path=ckpt)
    exports = model.export(run_dir)
    metrics = {k: float(v) for k, v in trainer.callback_metrics.items()}
    write_run_info(run_dir, exports=exports, final_metrics=metrics)
    log.info("Finished: %s", {k: round(v, 4) for k, v in metrics.items()})
    return {"run_dir": str(run_dir), "metrics": metrics, "exports": exports}


def main() -> None:
    run_app(train_task, "train")


if __name__ == "__main__":
    main()
