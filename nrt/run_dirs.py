"""Run folders ``outputs/<scene>/<stage>/<timestamp>-<pid>``: new for every run, or the
newest one with a checkpoint when resuming, so a resumed run continues in its own folder.

A resumed run must not overwrite what the first one wrote: its Hydra config goes to
``.hydra/<tag>/`` and its CSV log to ``csv/<tag>/``, with ``tag = resumed-<timestamp>``
(:func:`resume_tag`); TensorBoard adds new event files beside the old ones.

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

LAST_CKPT = Path("checkpoints") / "last.ckpt"
RUN_FILE = "run.json"
"""What nrt-train records about a run (stage, scene, dataset, environments, exports)."""

RESUMED_PREFIX = "resumed-"

SWEEP_FILE = "multirun.yaml"
"""What Hydra writes into a sweep's folder before its first job."""

_chosen: dict[tuple[str, str], str] = {}
_tags: dict[str, str] = {}
_created: dict[Path, Path] = {}  # folder new_run_dir named -> its nearest existing ancestor


def new_run_dir(base: str | Path) -> str:
    """``<base>/<timestamp>-<pid>``: unique, so runs never overwrite each other."""
    path = f"{base}/{time.strftime('%Y-%m-%d_%H-%M-%S')}-{os.getpid()}"
    folder = Path(os.path.abspath(path))
    _created[folder] = next(p for p in folder.parents if p.exists())
    return path


def latest_run_with_checkpoint(base: str | Path) -> Path | None:
    """The run folder under ``base`` whose ``checkpoints/last.ckpt`` is newest."""
    runs = [p.parent.parent for p in Path(base).glob(f"*/{LAST_CKPT}")]
    return max(runs, key=lambda r: (r / LAST_CKPT).stat().st_mtime, default=None)


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


def sweep_dir(base: str) -> str:
    """Resolver ``${nrt_sweep_dir:base}``: ``<base>/<timestamp>-<pid>``, the same answer for
    the whole process (Hydra resolves it for the sweep and again for each job)."""
    key = ("sweep", str(base))
    if key not in _chosen:
        _chosen[key] = new_run_dir(base)
    return _chosen[key]


def resume_tag(resume) -> str:
    """Resolver ``${nrt_resume_tag:resume}``: ``""`` for a new run, else ``resumed-<time>``."""
    if resume in (None, False):
        return ""
    return _tags.setdefault(str(resume),
                            f"{RESUMED_PREFIX}{time.strftime('%Y-%m-%d_%H-%M-%S')}")


def discard_failed_start(run_dir: str | Path, config_subdir: str | None, since: float,
                         sweep_job: bool = False) -> None:
    """Undo what a start that failed wrote into ``run_dir``, unless it saved a checkpoint
    after ``since`` (then it trained, and its folder is a run): a folder that this process
    named (:func:`new_run_dir`) goes, with the folders above it that did not exist before
    and are empty now; a multirun job's folder (``sweep_job``: Hydra made ``<sweep>/<n>`` for
    this job) goes, and its sweep's folder too when it holds nothing but Hydra's
    ``multirun.yaml``; in a resumed run's folder only this start's config copy
    (``config_subdir``, ``.hydra/resumed-<time>``) goes."""
    run_dir = Path(os.path.abspath(run_dir))
    if any(p.stat().st_mtime >= since for p in (run_dir / "checkpoints").glob("*.ckpt")):
        return
    if run_dir in _created:
        _remove_created(run_dir)
    elif sweep_job:
        shutil.rmtree(run_dir, ignore_errors=True)
        sweep = run_dir.parent
        if sweep in _created and all(p.name == SWEEP_FILE for p in sweep.iterdir()):
            _remove_created(sweep)
    elif config_subdir and Path(config_subdir).name.startswith(RESUMED_PREFIX):
        shutil.rmtree(run_dir / config_subdir, ignore_errors=True)


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
    """Merge ``info`` into the run folder's ``run.json``."""
    (Path(run_dir) / RUN_FILE).write_text(json.dumps({**read_run_info(run_dir), **info},
                                                     indent=1))


def eval_dir(run, output_dir: str, kind: str = "eval") -> str:
    """Resolver ``${nrt_eval_dir:run,output_dir[,kind]}``: ``<run>/<kind>/<timestamp>-<pid>``
    for a run folder, else ``<output_dir>/<kind>/<timestamp>-<pid>`` (also for a run folder
    that does not exist, which the command then reports without creating it); never an
    existing folder. ``kind`` is ``eval`` (nrt-eval) or ``sample`` (nrt-sample)."""
    given = run not in (None, "", "None") and Path(str(run)).expanduser().is_dir()
    base = (Path(str(run)).expanduser() if given else Path(output_dir)) / str(kind)
    return _chosen.setdefault((str(kind), str(base)), new_run_dir(base))
