"""What every nrt command does before and around its Hydra task.

- registers the OmegaConf resolvers the configs use (``nrt_pid``, ``nrt_run_dir``,
  ``nrt_sweep_dir``, ``nrt_job_subdir``, ``nrt_eval_dir``, ``nrt_resume_tag``, and
  ``nrt_name`` and ``nrt_folder``, which refuse a name that would leave the output folder
  and a folder that cannot take files, before Hydra creates any folder, and
  ``nrt_scaled_steps``, a step count times a checked factor);
- tunes glibc malloc so large per-step temporaries are reused instead of being mmap'd
  and unmapped every step (docs/conventions.md, "Runtime"; 3-4x faster training steps on CPU);
- lets idle OpenMP threads sleep instead of spin (``OMP_WAIT_POLICY=PASSIVE``, unless set):
  on a machine whose cores are shared, spinning threads made a training step 10x slower
  (2.2 s against 0.19 s, measured with another process busy on one of two cores);
- turns :class:`~nrt.errors.NrtError` and every config mistake that Hydra or OmegaConf
  reports (an unknown key or option, an unreadable override, an unresolvable
  interpolation, a ``_target_`` that cannot be built: :mod:`nrt.cli.config_errors`) into a
  one-paragraph ``nrt: error:`` message and exit status 2 instead of a traceback, and
  removes the run folder such a failed start created
  (:func:`nrt.run_dirs.discard_failed_start`); output that cannot be written (a full disk)
  ends the same way, naming the file (:mod:`nrt.files`);
- builds nrt's C++ extensions under ``<paths.output_dir>/.cache/extensions`` unless
  ``NRT_EXTENSIONS_DIR`` is set (:func:`keep_extensions_in`).
"""

from __future__ import annotations

import ctypes
import ctypes.util
import logging
import os
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import NoReturn

import hydra
from hydra.core.hydra_config import HydraConfig
from hydra.types import RunMode
from omegaconf import DictConfig, OmegaConf

from nrt import run_dirs
from nrt.cli.config_errors import config_mistake
from nrt.cli.schema import check_schema_keys
from nrt.errors import ConfigError, NrtError
from nrt.files import check_name, check_output_folder, write_failure

log = logging.getLogger(__name__)

CONFIG_DIR = Path(__file__).resolve().parents[2] / "conf"

_M_TRIM_THRESHOLD, _M_MMAP_THRESHOLD = -1, -3

FULL_ERROR = "HYDRA_FULL_ERROR"
"""With it set, Hydra re-raises what fails instead of printing it and exiting with status 1."""


def tune_allocator() -> bool:
    """Raise glibc's mmap and trim thresholds; returns False where glibc is absent."""
    if os.environ.get("NRT_KEEP_MALLOC"):
        return False
    name = ctypes.util.find_library("c")
    try:
        libc = ctypes.CDLL(name)
        mallopt = libc.mallopt
    except (OSError, AttributeError, TypeError):
        return False
    mallopt.argtypes, mallopt.restype = [ctypes.c_int, ctypes.c_int], ctypes.c_int
    big = 2**31 - 1
    trim_ok = mallopt(_M_TRIM_THRESHOLD, big) == 1
    # glibc refuses mmap thresholds above HEAP_MAX/2 (32 MiB on 64-bit): take the largest.
    mmap_ok = mallopt(_M_MMAP_THRESHOLD, big) == 1 or mallopt(_M_MMAP_THRESHOLD, 2**25) == 1
    return trim_ok and mmap_ok


def register_resolvers() -> None:
    """Register the OmegaConf resolvers that conf/ uses (its schemas are stored in Hydra's
    ConfigStore when this module imports :mod:`nrt.cli.schema`)."""
    if not OmegaConf.has_resolver("nrt_pid"):
        OmegaConf.register_new_resolver("nrt_pid", lambda: os.getpid())
    if not OmegaConf.has_resolver("nrt_run_dir"):
        OmegaConf.register_new_resolver("nrt_run_dir", run_dirs.run_dir)
    if not OmegaConf.has_resolver("nrt_eval_dir"):
        OmegaConf.register_new_resolver("nrt_eval_dir", run_dirs.eval_dir)
    if not OmegaConf.has_resolver("nrt_sweep_dir"):
        OmegaConf.register_new_resolver("nrt_sweep_dir", run_dirs.sweep_dir)
    if not OmegaConf.has_resolver("nrt_job_subdir"):
        OmegaConf.register_new_resolver("nrt_job_subdir", run_dirs.job_subdir)
    if not OmegaConf.has_resolver("nrt_resume_tag"):
        OmegaConf.register_new_resolver("nrt_resume_tag", run_dirs.resume_tag)
    if not OmegaConf.has_resolver("nrt_name"):
        OmegaConf.register_new_resolver("nrt_name", lambda key, value: check_name(key, value))
    if not OmegaConf.has_resolver("nrt_folder"):
        OmegaConf.register_new_resolver("nrt_folder", _checked_folder)
    if not OmegaConf.has_resolver("nrt_scaled_steps"):
        OmegaConf.register_new_resolver("nrt_scaled_steps", _scaled_steps)


def _scaled_steps(key: str, steps: int, scale: float) -> int:
    """Resolver ``${nrt_scaled_steps:key,steps,scale}``: ``steps x scale`` rounded, once the
    factor (the config key ``key``) is found to be a positive number."""
    if not isinstance(scale, int | float) or isinstance(scale, bool) or scale <= 0:
        raise ConfigError(f"{key}={scale}: must be a number > 0, the factor on "
                          f"budget.ea.steps ({steps}) that gives the run's steps.")
    return round(steps * scale) if isinstance(steps, int | float) else steps


def _checked_folder(key: str, folder: str) -> str:
    """Resolver ``${nrt_folder:key,folder}``: ``folder`` once :func:`check_output_folder`
    found that files can be created in it."""
    check_output_folder(folder, key)
    return folder


def _log_to_files(message: str) -> None:
    """Record an error in the run's log file(s) without repeating it on the console, where
    the one-paragraph ``nrt: error:`` message already says it."""
    record = log.makeRecord(log.name, logging.ERROR, __file__, 0, "%s", (message,), None)
    for handler in logging.getLogger().handlers:
        if isinstance(handler, logging.FileHandler):
            handler.handle(record)


def _set_env(name: str, value: str | None) -> None:
    if value is None:
        os.environ.pop(name, None)
    else:
        os.environ[name] = value


def _fail(exc: NrtError) -> NoReturn:
    print(f"\nnrt: error: {exc}", file=sys.stderr)
    sys.exit(2)


def keep_extensions_in(output_dir: str | None) -> None:
    """Build nrt's C++ extensions (:func:`nrt.compile.load_extension`) under
    ``<output_dir>/.cache/extensions``, beside inductor's kernels, unless
    ``NRT_EXTENSIONS_DIR`` is set: a command writes nothing outside its output folder."""
    from nrt.compile import EXTENSIONS_DIR_ENV

    if output_dir:
        os.environ.setdefault(EXTENSIONS_DIR_ENV, str(Path(output_dir) / ".cache" / "extensions"))


def run_app(task: Callable[[DictConfig], object], config_name: str,
            command: str | None = None,
            first_check: Callable[[DictConfig], object] | None = None) -> None:
    """Run ``task`` as a Hydra app over ``conf/<config_name>.yaml`` (the command
    ``command``, by default ``nrt-<config_name>``); config mistakes and :class:`NrtError`
    end in ``nrt: error:`` with status 2. ``first_check`` runs before the config is
    resolved: a mistake whose consequence is an unresolvable key is named as itself."""
    if not CONFIG_DIR.is_dir():
        sys.exit(f"nrt: config folder '{CONFIG_DIR}' not found. Install nrt from its source "
                 "checkout in editable mode (pip install -e .), which keeps conf/ beside nrt/.")
    register_resolvers()
    tune_allocator()
    os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")  # before torch starts OpenMP
    started = time.time()
    command = command or f"nrt-{config_name}"
    # Hydra hands us what fails while it composes the config only with HYDRA_FULL_ERROR
    # set. The task itself runs with the user's setting, so that Hydra reports a bug in it
    # as before; a user who set HYDRA_FULL_ERROR sees Hydra's own errors.
    user_full_error = os.environ.get(FULL_ERROR)
    os.environ[FULL_ERROR] = "1"

    @hydra.main(version_base="1.3", config_path=str(CONFIG_DIR), config_name=config_name)
    def _main(cfg: DictConfig):
        tune_allocator()  # again in a launcher's worker process, which runs jobs without run_app
        _set_env(FULL_ERROR, user_full_error)
        try:
            try:
                # every interpolation resolves, or the mistake names its key, typed settings
                # hold only their schema's keys, and every scalar option holds a value a run
                # can use, before the task
                if first_check is not None:
                    first_check(cfg)
                OmegaConf.to_container(cfg, resolve=True)
                from nrt.cli.checks import check_options  # it imports CONFIG_DIR from here

                check_schema_keys(cfg)
                check_options(cfg)
                keep_extensions_in(OmegaConf.select(cfg, "paths.output_dir"))
                result = task(cfg)
            except Exception as exc:
                mistake = config_mistake(exc, command) or \
                    write_failure(exc, HydraConfig.get().runtime.output_dir)
                if mistake is None:
                    raise
                raise mistake from None
        except NrtError as exc:
            _log_to_files(str(exc))
            hydra_cfg = HydraConfig.get()
            sweep = hydra_cfg.sweep.dir if hydra_cfg.mode == RunMode.MULTIRUN else None
            run_dirs.discard_failed_start(hydra_cfg.runtime.output_dir, hydra_cfg.output_subdir,
                                          started, sweep)
            _fail(exc)
        os.environ[FULL_ERROR] = "1"  # a multirun composes the next job's config
        return result

    try:
        _main()
    except Exception as exc:
        mistake = None if user_full_error else config_mistake(exc, command)
        if mistake is None:
            raise
        _fail(mistake)
    finally:
        _set_env(FULL_ERROR, user_full_error)
