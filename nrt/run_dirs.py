"""Run folders ``outputs/<scene>/<stage>/<timestamp>-<pid>``: new for every run, or the
newest one with a checkpoint when resuming, so a resumed run continues in its own folder.

A resumed run must not overwrite what the first one wrote: its Hydra config goes to
``.hydra/<tag>/`` and its CSV log to ``csv/<tag>/``, with ``tag = resumed-<timestamp>``
(:func:`resume_tag`); TensorBoard adds new event files beside the old ones.

In a multirun (``nrt-train -m``) every job gets ``outputs/multirun/<timestamp>-<pid>/<n>``;
with ``resume=true`` each job continues instead in the newest earlier job folder of any
sweep whose overrides equal its own (``resume`` aside, and any other key of
``hydra.job.config.override_dirname.exclude_keys``) and that saved a checkpoint
(:func:`job_subdir`), and the new sweep folder keeps only Hydra's ``multirun.yaml``. The
sweep folder is one for all jobs, also where a launcher runs them in other processes
(``NRT_SWEEP_DIR``, :func:`sweep_dir`); a job started again in its own folder, which holds
its checkpoint (a cluster re-queued it), continues there as ``resume=true`` would
(:func:`continuing_job`).

A start that fails (a config mistake, a missing checkpoint) leaves nothing behind:
:func:`discard_failed_start` removes the folder it created, or a resumed run's config copy;
in a multirun the job's folder ``<sweep>/<n>``, and the sweep's folder
``outputs/multirun/<timestamp>-<pid>`` (:func:`sweep_dir`) when no job left anything in it.
"""

from __future__ import annotations

import json
import os
import shutil
import time
from pathlib import Path

from nrt.files import check_output_folder, write_text_atomic

LAST_CKPT = Path("checkpoints") / "last.ckpt"
RUN_FILE = "run.json"
"""What nrt-train records about a run (stage, scene, dataset, environments, exports)."""

RESUMED_PREFIX = "resumed-"

SWEEP_FILE = "multirun.yaml"
"""What Hydra writes into a sweep's folder before its first job."""

SWEEP_ENV = "NRT_SWEEP_DIR"
"""The sweep folder, for the processes a sweep starts (:func:`sweep_dir`)."""

_chosen: dict[tuple[str, str], str] = {}
_tags: dict[str, str] = {}
_created: dict[Path, Path] = {}  # folder new_run_dir named -> its nearest existing ancestor


def new_run_dir(base: str | Path, key: str = "paths.output_dir") -> str:
    """``<base>/<timestamp>-<pid>``: unique, so runs never overwrite each other. A ``base``
    that cannot be created or written (a file, a read-only folder) is refused, naming the
    config key ``key`` it comes from, before Hydra creates the folder."""
    check_output_folder(base, key)
    path = f"{base}/{time.strftime('%Y-%m-%d_%H-%M-%S')}-{os.getpid()}"
    folder = Path(os.path.abspath(path))
    _created[folder] = next(p for p in folder.parents if p.exists())
    return path


def latest_run_with_checkpoint(base: str | Path, dataset: str | None = None) -> Path | None:
    """The run folder under ``base`` whose ``checkpoints/last.ckpt`` is newest; with
    ``dataset`` (a dataset folder's name, :func:`run_dataset`) only among the runs that
    trained on that dataset."""
    runs = [p.parent.parent for p in Path(base).glob(f"*/{LAST_CKPT}")]
    if dataset is not None:
        runs = [r for r in runs if run_dataset(r) == dataset]
    return max(runs, key=lambda r: (r / LAST_CKPT).stat().st_mtime, default=None)


def run_dataset(run_dir: str | Path) -> str | None:
    """The name of the dataset folder a run trained on (``<scene>-<hash>`` for a rendered
    scene, as its ``run.json`` records it); None where it records none (a family)."""
    folder = read_run_info(run_dir).get("dataset_dir")
    return Path(folder).name if folder else None


def run_dir(base: str, resume) -> str:
    """Resolver ``${nrt_run_dir:base,resume}``; the same answer for the whole process."""
    key = (str(base), str(resume))
    if key not in _chosen:
        chosen = None
        if resume is True:
            chosen = latest_run_with_checkpoint(base)
        elif resume not in (None, False) and Path(str(resume)).is_file():
            chosen = Path(str(resume)).resolve().parent.parent
        _chosen[key] = str(chosen) if chosen is not None else new_run_dir(base)
    return _chosen[key]


def sweep_dir(base: str, *, _root_=None) -> str:
    """Resolver ``${nrt_sweep_dir:base}``: ``<base>/<timestamp>-<pid>``, the same answer for
    the whole process (Hydra resolves it for the sweep and again for each job) and for the
    processes it starts (a launcher's workers, a cluster's jobs resolve it again): a
    sweep puts its folder into their environment as ``NRT_SWEEP_DIR``, and a folder found
    there is the answer. Setting it runs a sweep again in that folder, where the jobs that
    saved a checkpoint continue (:func:`continuing_job`). ``_root_``: the config resolved
    (OmegaConf passes it), whose ``hydra.mode`` tells a sweep from a config composed
    elsewhere (a test's), which leaves the environment alone."""
    from hydra.types import RunMode
    from omegaconf import OmegaConf

    key = ("sweep", str(base))
    if key not in _chosen:
        _chosen[key] = os.environ.get(SWEEP_ENV) or new_run_dir(base)
    if _root_ is not None and OmegaConf.select(_root_, "hydra.mode") == RunMode.MULTIRUN:
        os.environ[SWEEP_ENV] = os.path.abspath(_chosen[key])
    return _chosen[key]


def _multirun_job():
    """Hydra's config of the multirun job this process runs; None for anything else (a
    single run, a config composed by a test)."""
    from hydra.core.hydra_config import HydraConfig
    from hydra.types import RunMode

    if not HydraConfig.initialized():
        return None
    hydra_cfg = HydraConfig.get()
    return hydra_cfg if hydra_cfg.mode == RunMode.MULTIRUN else None


def continuing_job() -> bool:
    """Whether this process runs a multirun job, not asked to resume, in a folder that
    already holds its ``checkpoints/last.ckpt``: the same job of the same sweep started
    again (submitit re-queued it after a preemption or its time limit, or the sweep ran
    again with ``NRT_SWEEP_DIR``). Such a job continues from that checkpoint, as
    ``resume=true`` would, under a ``resumed-<time>`` tag (:func:`resume_tag`)."""
    from omegaconf import OmegaConf

    hydra_cfg = _multirun_job()
    folder = OmegaConf.select(hydra_cfg, "runtime.output_dir") if hydra_cfg else None
    return bool(folder) and (Path(str(folder)) / LAST_CKPT).is_file()


def _kept(overrides, exclude_keys) -> list[str]:
    """Task overrides without those of ``exclude_keys`` (``resume``), sorted."""
    def key(o: str) -> str:
        return o.split("=", 1)[0].lstrip("+~")
    return sorted(str(o) for o in overrides if key(str(o)) not in set(exclude_keys))


def earlier_job(multirun: str | Path, overrides, exclude_keys=("resume",),
                exclude_sweep: str | Path | None = None) -> Path | None:
    """The newest job folder ``<multirun>/<sweep>/<n>`` (outside the sweep ``exclude_sweep``)
    that saved ``checkpoints/last.ckpt`` and whose task overrides (``.hydra/overrides.yaml``)
    equal ``overrides``, both without the keys ``exclude_keys``."""
    from omegaconf import OmegaConf

    wanted, found = _kept(overrides, exclude_keys), []
    for ckpt in Path(multirun).glob(f"*/*/{LAST_CKPT}"):
        job = ckpt.parent.parent
        record = job / ".hydra" / "overrides.yaml"
        if exclude_sweep is not None and job.parent.resolve() == Path(exclude_sweep).resolve():
            continue
        if record.is_file() and _kept(OmegaConf.load(record), exclude_keys) == wanted:
            found.append(job)
    return max(found, key=lambda j: (j / LAST_CKPT).stat().st_mtime, default=None)


def job_subdir(num, resume) -> str:
    """Resolver ``${nrt_job_subdir:num,resume}`` (``hydra.sweep.subdir``, resolved while
    Hydra's config is the job's): the job's number; with ``resume=true`` the absolute path
    of the :func:`earlier_job` with this job's overrides, the keys of
    ``hydra.job.config.override_dirname.exclude_keys`` left out (``resume``; add e.g.
    ``budget.ea.steps`` to continue with more steps), when there is one. Hydra joins the
    answer to the sweep's folder, which leaves an absolute path whole."""
    from hydra.core.hydra_config import HydraConfig

    hydra_cfg = HydraConfig.get()
    key = ("job", str(hydra_cfg.sweep.dir), str(num))
    if key not in _chosen:
        found = earlier_job(Path(str(hydra_cfg.sweep.dir)).parent, hydra_cfg.overrides.task,
                            hydra_cfg.job.config.override_dirname.exclude_keys,
                            exclude_sweep=hydra_cfg.sweep.dir) if resume is True else None
        _chosen[key] = str(found.resolve()) if found is not None else str(num)
    return _chosen[key]


def resume_tag(resume) -> str:
    """Resolver ``${nrt_resume_tag:resume}``: ``""`` for a new run, else ``resumed-<time>``
    (also for a :func:`continuing_job`)."""
    if resume in (None, False):
        if not continuing_job():
            return ""
        resume = f"job:{_multirun_job().runtime.output_dir}"
    return _tags.setdefault(str(resume),
                            f"{RESUMED_PREFIX}{time.strftime('%Y-%m-%d_%H-%M-%S')}")


def discard_failed_start(run_dir: str | Path, config_subdir: str | None, since: float,
                         sweep: str | Path | None = None) -> None:
    """Undo what a start that failed wrote into ``run_dir``, unless it saved a checkpoint
    after ``since`` (then it trained, and its folder is a run): a folder that this process
    named (:func:`new_run_dir`) goes, with the folders above it that did not exist before
    and are empty now; a multirun job's new folder ``<sweep>/<n>`` goes (``sweep``: the
    sweep's folder, given for a multirun job), and the sweep's folder too when it holds
    nothing but Hydra's ``multirun.yaml``; in a resumed run's folder (a single run's, an
    earlier sweep's job that a multirun resumed, a job continuing in its own folder) only
    this start's config copy (``config_subdir``, ``.hydra/resumed-<time>``) goes."""
    run_dir = Path(os.path.abspath(run_dir))
    if any(p.stat().st_mtime >= since for p in (run_dir / "checkpoints").glob("*.ckpt")):
        return
    sweep = Path(os.path.abspath(sweep)) if sweep is not None else None
    if run_dir in _created:
        _remove_created(run_dir)
    elif sweep is not None and run_dir.parent == sweep and not (run_dir / LAST_CKPT).exists():
        shutil.rmtree(run_dir, ignore_errors=True)
    elif config_subdir and Path(config_subdir).name.startswith(RESUMED_PREFIX):
        shutil.rmtree(run_dir / config_subdir, ignore_errors=True)
    if sweep in _created and sweep.is_dir() and \
            all(p.name == SWEEP_FILE for p in sweep.iterdir()):
        _remove_created(sweep)


def _remove_created(folder: Path) -> None:
    """Remove a folder :func:`new_run_dir` named, and the folders above it that did not
    exist before and are empty now."""
    shutil.rmtree(folder, ignore_errors=True)
    parent = folder.parent
    while parent != _created[folder] and parent.is_dir() and not any(parent.iterdir()):
        parent.rmdir()
        parent = parent.parent


def read_run_info(run_dir: str | Path) -> dict:
    """The run folder's ``run.json`` ({} where there is none yet)."""
    path = Path(run_dir) / RUN_FILE
    return json.loads(path.read_text()) if path.is_file() else {}


def write_run_info(run_dir: str | Path, **info) -> None:
    """Merge ``info`` into the run folder's ``run.json`` (replaced atomically)."""
    write_text_atomic(Path(run_dir) / RUN_FILE,
                      json.dumps({**read_run_info(run_dir), **info}, indent=1),
                      "the run record")


def eval_dir(run, output_dir: str, kind: str = "eval") -> str:
    """Resolver ``${nrt_eval_dir:run,output_dir[,kind]}``: ``<run>/<kind>/<timestamp>-<pid>``
    for a run folder, else ``<output_dir>/<kind>/<timestamp>-<pid>`` (also for a run folder
    that does not exist, which the command then reports without creating it); never an
    existing folder. ``kind`` is ``eval`` (nrt-eval) or ``sample`` (nrt-sample)."""
    given = run not in (None, "", "None") and Path(str(run)).expanduser().is_dir()
    base = (Path(str(run)).expanduser() if given else Path(output_dir)) / str(kind)
    key = (str(kind), str(base))
    if key not in _chosen:
        _chosen[key] = new_run_dir(base, "run" if given else "paths.output_dir")
    return _chosen[key]
