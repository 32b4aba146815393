"""``nrt-train``: train one stage on a scene (rendering its dataset first when missing).

Short and linear, in the lightning-hydra-template manner: compose, seed, model (so that
what the config alone decides is refused before any rendering), data, callbacks,
loggers, trainer, fit (resuming when asked), export. Lightning, torch and
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
from nrt.cli.run_dirs import LAST_CKPT, latest_run_with_checkpoint, write_run_info
from nrt.errors import NrtError

log = logging.getLogger(__name__)


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


def resolve_ea_checkpoint(cfg: DictConfig) -> None:
    """Stage 2 modulates stage 1's density: with ``init.source=ea`` and no
    ``init.ea_ckpt``, take the newest EA run of the same scene that saved a checkpoint."""
    if OmegaConf.select(cfg, "model.density.source") != "ea" or cfg.init.ea_ckpt:
        return
    base = Path(cfg.paths.output_dir) / cfg.scene.name / "ea"
    run = latest_run_with_checkpoint(base)
    if run is None:
        raise NrtError(f"stage={cfg.stage.name} starts from the EA density of scene "
                       f"'{cfg.scene.name}', but no EA run under '{base}' saved "
                       f"{LAST_CKPT}. Run `nrt-train stage=ea scene={cfg.scene.name}` first, "
                       "pass init.ea_ckpt=<path/to/last.ckpt>, or use init=none for the "
                       "single-stage ablation.")
    cfg.init.ea_ckpt = str(run / LAST_CKPT)
    log.info("Stage %s starts from EA checkpoint %s", cfg.stage.name, cfg.init.ea_ckpt)


def train_task(cfg: DictConfig) -> dict:
    import lightning as L

    from nrt.data.render import ensure_dataset

    run_dir = Path(HydraConfig.get().runtime.output_dir)
    L.seed_everything(cfg.seed, workers=True)
    # What the config alone decides is refused before any rendering or data loading: a
    # missing EA run or resume checkpoint, and the model's own checks (e.g. stage 2 on
    # truncated scattering orders).
    resolve_ea_checkpoint(cfg)
    ckpt = resume_checkpoint(cfg, run_dir)
    model = hydra.utils.instantiate(cfg.model, _convert_="all")
    dataset_dir = ensure_dataset(OmegaConf.to_container(cfg.scene, resolve=True),
                                 cfg.paths.data_dir, variant=cfg.render.variant,
                                 progress=cfg.render.progress)
    datamodule = hydra.utils.instantiate(cfg.data, dataset_dir=str(dataset_dir))
    datamodule.setup()
    write_run_info(run_dir, stage=cfg.stage.name, scene=cfg.scene.name,
                   dataset_dir=str(Path(dataset_dir).resolve()),
                   environments=datamodule.train_data.environments_used())
    callbacks = [hydra.utils.instantiate(c) for c in cfg.callbacks.values()]
    loggers = [hydra.utils.instantiate(lg) for lg in cfg.logger.values()]
    trainer = hydra.utils.instantiate(cfg.trainer, callbacks=callbacks, logger=loggers)
    log.info("Run folder %s; dataset %s%s", run_dir, dataset_dir,
             f"; resuming from {ckpt}" if ckpt else "")
    trainer.fit(model, datamodule=datamodule, ckpt_path=ckpt)
    exports = model.export(run_dir) if hasattr(model, "export") else {}
    metrics = {k: float(v) for k, v in trainer.callback_metrics.items()}
    write_run_info(run_dir, exports=exports, final_metrics=metrics)
    log.info("Finished: %s", {k: round(v, 4) for k, v in metrics.items()})
    return {"run_dir": str(run_dir), "metrics": metrics, "exports": exports}


def main() -> None:
    run_app(train_task, "train")


if __name__ == "__main__":
    main()
