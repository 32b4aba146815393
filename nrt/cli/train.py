"""``nrt-train``: train one stage on a scene (rendering its dataset first when missing).

Short and linear, in the lightning-hydra-template manner: compose, threads, seed, checks,
model and callbacks (so that what the config alone decides is refused before any
rendering), data, loggers, trainer, fit (resuming when asked), export. The EA checkpoint a
stage starts from is resolved to an absolute path and recorded in ``run.json`` and in the
saved ``.hydra/config.yaml`` (``init.ea_ckpt``); ``mode=generative`` trains on every member
of a scene family (``scene=family``) and records the family folder and its members. A run
in several processes (``trainer=ddp_cpu``, ``trainer=ddp``) runs this task on every rank:
rank 0 decides and writes, the ranks it starts take its decisions (:mod:`nrt.distributed`).
A resumed run that had already finished is left as it is. Lightning, torch and Mitsuba are
imported inside the task, so ``--cfg``, ``--help`` and config errors answer at once.
"""

from __future__ import annotations

import logging
from pathlib import Path

import hydra
from hydra.core.hydra_config import HydraConfig
from hydra.types import RunMode
from omegaconf import DictConfig, OmegaConf

from nrt.cli.checks import (
    check_arguments,
    check_budget,
    check_mode,
    check_mode_fits,
    check_objectives,
    check_processes,
    processes,
)
from nrt.cli.common import run_app
from nrt.errors import NrtError
from nrt.files import check_output_folder, write_text_atomic
from nrt.run_dirs import LAST_CKPT, continuing_job, read_run_info, write_run_info

log = logging.getLogger(__name__)


def resume_checkpoint(cfg: DictConfig, run_dir: Path) -> str | None:
    """Checkpoint to continue from: ``resume=true`` -> this run folder's last.ckpt (the
    run-dir resolver picked the latest run; in a multirun, the job-folder resolver picked
    the newest earlier job with the same overrides), ``resume=<path>`` -> that file; a
    sweep's job started again in its own folder (:func:`nrt.run_dirs.continuing_job`: a
    cluster re-queued it) -> that folder's last.ckpt."""
    if cfg.resume in (None, False):
        if continuing_job():
            log.info("Job folder %s holds %s: this job was started again and continues from "
                     "it", run_dir, LAST_CKPT)
            return str(run_dir / LAST_CKPT)
        return None
    ckpt = run_dir / LAST_CKPT if cfg.resume is True else Path(str(cfg.resume))
    hydra_cfg = HydraConfig.get()
    if not ckpt.is_file() and cfg.resume is True and hydra_cfg.mode == RunMode.MULTIRUN:
        excluded = list(hydra_cfg.job.config.override_dirname.exclude_keys)
        raise NrtError(f"resume=true in a multirun continues each job in the newest earlier "
                       f"job folder ({Path(hydra_cfg.sweep.dir).parent}/<sweep>/<n>) with the "
                       f"same overrides, {excluded} left out, that saved {LAST_CKPT}; job "
                       f"{hydra_cfg.job.num} (overrides: {hydra_cfg.job.override_dirname}) has "
                       "none. To continue with another value of a key (more steps), add it: "
                       "'hydra.job.config.override_dirname.exclude_keys=[resume,<key>]'. Run "
                       "jobs that never saved a checkpoint without resume=true.")
    if not ckpt.is_file():
        raise NrtError(f"resume={cfg.resume}: no checkpoint at '{ckpt}'. resume=true continues "
                       f"the newest run of scene '{cfg.scene.name}', stage '{cfg.stage.name}' "
                       "that saved checkpoints/last.ckpt; pass resume=<path/to/file.ckpt> for "
                       "another, or drop resume to start afresh.")
    return str(ckpt)


def resolve_ea_checkpoint(cfg: DictConfig, recorded: str | None = None) -> str | None:
    """The EA checkpoint a stage starts from (:func:`nrt.stages.start.resolve_ea_checkpoint`:
    ``init.ea_ckpt``, else ``recorded`` by a resumed run, else the scene's newest EA run on
    the same dataset), set into ``cfg.init.ea_ckpt`` as an absolute path; None for a stage
    that reads none."""
    from nrt.data.render import dataset_name
    from nrt.stages.start import resolve_ea_checkpoint as resolve

    density = OmegaConf.select(cfg, "model.density")
    if density is None:
        return None
    scene = OmegaConf.to_container(cfg.scene, resolve=True)
    path = resolve(OmegaConf.to_container(density, resolve=True), cfg.scene.name,
                   cfg.stage.name, cfg.paths.output_dir, recorded,
                   dataset_name(scene, cfg.paths.data_dir))
    if path is not None:
        cfg.init.ea_ckpt = path
        log.info("Stage %s starts from EA checkpoint %s", cfg.stage.name, path)
    return path


def finished_run(cfg: DictConfig, run_dir: Path) -> dict | None:
    """What a finished run returned (its folder, final metrics and exports, from
    ``run.json``) when the run in ``run_dir`` already trained all ``stage.steps``; None
    when it has steps left (a run killed, or one given more steps)."""
    info = read_run_info(run_dir)
    done = info.get("finished_step")
    if done is None or int(done) < int(cfg.stage.steps):
        return None
    log.info("Run %s finished at step %d of %d already: nothing to continue (raise the "
             "stage's steps to train on).", run_dir, done, cfg.stage.steps)
    return {"run_dir": str(run_dir), "metrics": info.get("final_metrics", {}),
            "exports": info.get("exports", {})}


def save_config(cfg: DictConfig, run_dir: Path) -> None:
    """Write ``cfg`` over the copy Hydra saved before the task ran (``.hydra/config.yaml``,
    or the resumed run's ``.hydra/<tag>/config.yaml``), so that it shows what the task
    resolved (the EA checkpoint)."""
    subdir = HydraConfig.get().output_subdir
    if subdir is not None:
        write_text_atomic(run_dir / str(subdir) / "config.yaml", OmegaConf.to_yaml(cfg),
                          "the run's config")


def set_threads(cfg: DictConfig) -> int | None:
    """Torch threads of this process from the ``threads`` key
    (:func:`nrt.distributed.job_threads`: in a sweep, a joblib launcher's ``n_jobs`` share
    the cores); the count set, None where torch keeps its default."""
    from nrt import distributed

    hydra_cfg = HydraConfig.get()
    multirun = hydra_cfg.mode == RunMode.MULTIRUN
    launcher = {key: OmegaConf.select(hydra_cfg, f"launcher.{key}") if multirun else None
                for key in ("n_jobs", "cpus_per_task", "tasks_per_node")}
    nodes = int(OmegaConf.select(cfg, "trainer.num_nodes") or 1)
    threads = distributed.job_threads(cfg.threads, launcher, max(1, processes(cfg) // nodes),
                                      distributed.usable_cores())
    if threads is not None:
        distributed.use_threads(threads)
    return threads


def train_task(cfg: DictConfig) -> dict:
    import lightning as L

    from nrt import distributed
    from nrt.data.family import ensure_family
    from nrt.data.render import ensure_dataset

    run_dir = Path(HydraConfig.get().runtime.output_dir)
    lead = distributed.is_rank_zero()  # rank 0 (or the only process) decides and writes
    threads = set_threads(cfg)
    L.seed_everything(cfg.seed, workers=True)  # a seed run_app checked (nrt.cli.checks)
    # What the config alone decides is refused before any rendering or data loading:
    # counts no run can use, a dataset cache that cannot take files, a missing EA run or
    # resume checkpoint, the checks of the model and callbacks themselves (e.g. stage 2 on
    # truncated scattering orders) and a stage that cannot train in several processes.
    check_budget(cfg)
    if not OmegaConf.select(cfg, "scene.path"):
        check_output_folder(cfg.paths.data_dir, "paths.data_dir")
    check_objectives(cfg)
    check_mode(cfg)
    check_arguments(cfg, HydraConfig.get().runtime.choices)
    check_processes(cfg, HydraConfig.get().runtime.choices)
    ckpt = resume_checkpoint(cfg, run_dir)
    finished = finished_run(cfg, run_dir) if ckpt else None
    if finished is not None:
        return finished
    ea_ckpt = resolve_ea_checkpoint(cfg, read_run_info(run_dir).get("ea_ckpt") if ckpt else None)
    if ea_ckpt is not None and lead:
        save_config(cfg, run_dir)
    model = hydra.utils.instantiate(cfg.model, _convert_="all")
    callbacks = [hydra.utils.instantiate(c) for c in cfg.callbacks.values()]
    scene = OmegaConf.to_container(cfg.scene, resolve=True)
    ensure = ensure_family if scene.get("family") is not None else ensure_dataset
    # ranks > 0 start once rank 0 has it: they find it in the cache
    dataset_dir = ensure(scene, cfg.paths.data_dir, variant=cfg.render.variant,
                         progress=cfg.render.progress and lead)  # a family: the family folder
    datamodule = hydra.utils.instantiate(cfg.data, dataset_dir=str(dataset_dir))
    datamodule.setup()
    if lead:
        write_run_info(run_dir, stage=cfg.stage.name, scene=cfg.scene.name, mode=cfg.mode.name,
                       **datamodule.run_info(), finished_step=None,
                       **({"ea_ckpt": ea_ckpt} if ea_ckpt is not None else {}))
    loggers = [hydra.utils.instantiate(lg) for lg in cfg.logger.values()]
    trainer = hydra.utils.instantiate(cfg.trainer, callbacks=callbacks, logger=loggers)
    distributed.pin_for_ranks(trainer, resume=ckpt, threads=threads,
                              **{"init.ea_ckpt": ea_ckpt})
    log.info("Run folder %s; dataset %s%s", run_dir, dataset_dir,
             f"; resuming from {ckpt}" if ckpt else "")
    with distributed.training_processes():
        trainer.fit(model, datamodule=datamodule, ckpt_path=ckpt)
        ranks = distributed.rank_records(trainer, model)  # every rank, together
    metrics = {k: float(v) for k, v in trainer.callback_metrics.items()}
    if not trainer.is_global_zero:
        return {"run_dir": str(run_dir), "metrics": metrics, "exports": {}}
    exports = model.export(run_dir)
    write_run_info(run_dir, exports=exports, final_metrics=metrics,
                   finished_step=trainer.global_step, world_size=len(ranks), ranks=ranks)
    log.info("Finished: %s", {k: round(v, 4) for k, v in metrics.items()})
    return {"run_dir": str(run_dir), "metrics": metrics, "exports": exports}


def main() -> None:
    run_app(train_task, "train", first_check=check_mode_fits)


if __name__ == "__main__":
    main()
