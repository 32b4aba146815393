"""Training in several processes, and everything that depends on a process's rank.

``trainer=ddp_cpu`` trains in 2 processes on the CPU (gloo), ``trainer=ddp`` in one per GPU
(NCCL); both use :class:`GradientAveraging`, and ``trainer=cpu`` / ``trainer=gpu`` are the
same code with one rank. The run is data parallel: every rank builds the same stage from
rank 0's parameters, draws its own ray batches and Monte Carlo samples
(:func:`rank_seed`), and before every optimizer step each gradient becomes its mean over
the ranks (:func:`average_gradients`), so all ranks take the same steps.

- Run folder: rank 0 is the process the user started. It resolves the run folder (a new
  one, the newest with ``resume=true``, a sweep job's), renders or finds the dataset and
  resolves the checkpoint it resumes from and the EA checkpoint it starts from. When
  training starts, Lightning starts ranks 1..N-1 with :func:`child_command`: nrt-train with
  the job's overrides, ``hydra.run.dir=<rank 0's folder>`` and rank 0's checkpoints
  (:meth:`GradientAveraging.pin`), so every rank works in one folder from the same files,
  in a single run and in a sweep's job alike.
- Rank zero only: ``run.json``, exports, the saved config, checkpoints and loggers
  (Lightning's), property metrics and the periodic re-render. A rank > 0 writes only its
  log, ``<job name>_rank<r>.log``.
- Metrics: each is the mean over the ranks (``sync_dist``), except ``time/*`` and
  ``memory/*``, rank 0's own (:func:`synced`).
- Budgets are per rank: each rank draws ``stage.rays_per_batch`` rays and every sample
  count of the preset a step, so N ranks draw N times a one-process run's rays per step.
  A one-process run at the same total rays per step is the comparison to make
  (``trainer=cpu budget.ea.rays_per_batch=<N x the ranks'>``).
"""

from __future__ import annotations

import hashlib
import os
import socket
import sys
from collections.abc import Iterable, Iterator, Mapping
from contextlib import contextmanager
from unittest import mock

import numpy as np
import torch
import torch.distributed as dist
from lightning.pytorch.strategies import DDPStrategy
from lightning.pytorch.strategies.launchers import subprocess_script

TRAIN_MODULE = "nrt.cli.train"
"""What ranks > 0 run, whatever started rank 0 (the console script, ``python -m``, a
launcher's worker)."""

SEED_BITS = 32
"""Bits of a rank's seed: torch's CPU generator (a Mersenne twister) keeps the low 32 bits of
the seed it is given, so seeds that differ above them draw the same numbers."""

UNSYNCED = ("time/", "memory/")
"""Metrics that are rank 0's own (clocks, timings, memory), not means over the ranks."""

LAUNCH_VARIABLES = ("MASTER_ADDR", "MASTER_PORT", "NODE_RANK", "LOCAL_RANK", "WORLD_SIZE",
                    "OMP_NUM_THREADS")
"""What launching the ranks puts into rank 0's environment."""


def is_rank_zero() -> bool:
    """Whether this process is rank 0 of its run (or its only process), from what launchers
    put into the environment: ``RANK`` (torchrun), ``LOCAL_RANK`` and ``NODE_RANK``
    (Lightning, for the ranks it starts), ``SLURM_PROCID`` (a job's tasks). For use before
    the trainer exists; after, ``trainer.is_global_zero``."""
    if "RANK" in os.environ:
        return int(os.environ["RANK"]) == 0
    if "LOCAL_RANK" in os.environ:
        return int(os.environ["LOCAL_RANK"]) == 0 and int(os.environ.get("NODE_RANK", 0)) == 0
    return int(os.environ.get("SLURM_PROCID", os.environ.get("JSM_NAMESPACE_RANK", 0))) == 0


def rank_seed(seed: int, rank: int) -> int:
    """The seed of rank ``rank``'s random draws in a run of seed ``seed``: ``seed`` on rank 0
    (a one-process run draws what rank 0 draws); on rank r > 0 a 32-bit seed that NumPy's
    ``SeedSequence`` mixes from ``(seed, r)``, so that no rank repeats another's draws and
    rank r of one run is not rank 0 of a neighbouring seed. 32 bits, because torch's CPU
    generator ignores the bits above them (``seed + r 2^32`` would draw rank 0's numbers)."""
    if int(rank) == 0:
        return int(seed)
    mixed = np.random.SeedSequence(int(seed), spawn_key=(int(rank),))
    return int(mixed.generate_state(1, np.uint32)[0])


def synced(name: str) -> bool:
    """Whether metric ``name`` is logged as its mean over the ranks (:data:`UNSYNCED`)."""
    return not name.startswith(UNSYNCED)


def process_count(trainer: Mapping) -> int:
    """How many processes a trainer config (``cfg.trainer``, resolved) trains in: its
    devices times its nodes under a strategy of several processes, else 1."""
    strategy = trainer.get("strategy")
    name = strategy.get("_target_", "") if isinstance(strategy, Mapping) else str(strategy)
    if not (name.endswith(".GradientAveraging") or name.startswith(("ddp", "fsdp", "deep"))):
        return 1
    devices = trainer.get("devices", "auto")
    if isinstance(devices, list | tuple):
        count = len(devices)
    elif str(devices).isdigit() and int(devices) > 0:
        count = int(devices)
    elif str(trainer.get("accelerator")) in ("gpu", "cuda"):
        count = torch.cuda.device_count()  # -1 or auto: every GPU
    elif str(devices) == "-1":
        count = os.cpu_count() or 1
    else:
        count = 1
    return max(1, count) * int(trainer.get("num_nodes") or 1)


def usable_cores() -> int:
    """The cores this process may run on (its CPU affinity, which SLURM sets)."""
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # not Linux
        return os.cpu_count() or 1


def job_threads(threads: int | None, launcher: Mapping | None, processes: int,
                cores: int) -> int | None:
    """Torch threads for each process of a job (the ``threads`` key): ``threads`` when
    given; else the ``cores`` (at most a submitit launcher's ``cpus_per_task``, which are
    each task's: a SLURM task of ``tasks_per_node`` is a process of its own) shared among
    the jobs a joblib launcher runs at once (``n_jobs``; -1: one per core) and the run's
    ``processes`` on this machine; None (torch's default) for a lone one-process run."""
    if threads is not None:
        return int(threads)
    launcher = launcher or {}
    jobs, cpus = launcher.get("n_jobs"), launcher.get("cpus_per_task")
    processes = max(1, processes // int(launcher.get("tasks_per_node") or 1))
    if not isinstance(jobs, int) or jobs == 0:
        jobs = 1
    elif jobs < 0:  # joblib's -1: as many as cores, -2: one fewer ...
        jobs = max(1, cores + 1 + jobs)
    if isinstance(cpus, int) and cpus > 0:
        cores = min(cores, cpus)
    elif jobs * processes == 1:
        return None
    return max(1, cores // (jobs * processes))


def use_threads(threads: int) -> None:
    """Run torch on ``threads`` threads, and tell the ranks started later (and Lightning,
    which then leaves the count alone) through ``OMP_NUM_THREADS``."""
    torch.set_num_threads(threads)
    os.environ["OMP_NUM_THREADS"] = str(threads)


def _quoted(value: object) -> str:
    """``value`` as a Hydra override's quoted string (a path may hold ``=``, ``,``)."""
    text = str(value)
    return f"'{text}'" if "'" not in text else '"' + text.replace('"', '\\"') + '"'


def child_command(rank: int, pinned: Mapping[str, object]) -> tuple[list[str], str]:
    """The command line and working folder of rank ``rank`` (> 0) of the Hydra job that runs
    in this process: nrt-train with the job's overrides (a sweep's job: its own values,
    not the sweep), the ``pinned`` overrides rank 0 decided (the checkpoint to resume
    from, the EA checkpoint), rank 0's run folder, no config copy, and the log file
    ``<job name>_rank<rank>.log``."""
    from hydra.core.hydra_config import HydraConfig

    hydra_cfg = HydraConfig.get()
    task = [str(o) for o in hydra_cfg.overrides.task
            if str(o).split("=", 1)[0].lstrip("+~") not in pinned]
    command = [sys.executable, "-m", TRAIN_MODULE, *task,
               *(f"{key}={_quoted(value) if isinstance(value, str) else value}"
                 for key, value in pinned.items()),
               f"hydra.run.dir={_quoted(hydra_cfg.runtime.output_dir)}",
               "hydra.output_subdir=null", f"hydra.job.name={hydra_cfg.job.name}_rank{rank}"]
    return command, str(hydra_cfg.runtime.cwd)


@torch.no_grad()
def broadcast_state(module: torch.nn.Module, src: int = 0) -> None:
    """Every parameter and buffer of ``module`` set to rank ``src``'s."""
    for tensor in [*module.parameters(), *module.buffers()]:
        data = tensor.data
        if data.numel() == 0:
            continue
        sent = data if data.is_contiguous() and data.dtype != torch.bool else \
            data.contiguous().to(torch.uint8 if data.dtype == torch.bool else data.dtype)
        dist.broadcast(sent, src)
        if sent is not data:
            data.copy_(sent)


@torch.no_grad()
def average_gradients(parameters: Iterable[torch.Tensor]) -> None:
    """Replace each parameter's gradient by its mean over the ranks. A rank without one
    counts zero; a parameter that no rank has a gradient for keeps none, so that the
    optimizer skips it as it does in one process (stage 2's medium during its light
    warm-up). One all-reduce per dtype, of the gradients laid end to end; shapes may change
    between steps (grids that double)."""
    params = list(dict.fromkeys(parameters))
    if not params or not (dist.is_available() and dist.is_initialized()):
        return
    world = dist.get_world_size()
    if world == 1:
        return
    present = torch.tensor([p.grad is not None for p in params], dtype=torch.float32,
                           device=params[0].device)
    dist.all_reduce(present)
    groups: dict[tuple, list[torch.Tensor]] = {}
    for p, count in zip(params, present.tolist(), strict=True):
        if count == 0:
            continue
        if p.grad is None:
            p.grad = torch.zeros_like(p)
        elif p.grad.is_sparse:
            p.grad = p.grad.to_dense()
        groups.setdefault((p.grad.dtype, p.grad.device), []).append(p)
    for group in groups.values():
        flat = torch.cat([p.grad.reshape(-1) for p in group])
        dist.all_reduce(flat)
        flat /= world
        offset = 0
        for p in group:
            size = p.grad.numel()
            p.grad.copy_(flat[offset:offset + size].view_as(p.grad))
            offset += size


class _RankProcesses(subprocess_script._SubprocessScriptLauncher):
    """Lightning's launcher of this node's ranks 1..N-1, each started by
    :func:`child_command` instead of rank 0's own command line, which in a sweep would
    start the whole sweep again and in a launcher's worker would not start nrt-train."""

    def __init__(self, strategy: GradientAveraging, *args) -> None:
        super().__init__(*args)
        self._pins = strategy

    def _call_children_scripts(self) -> None:
        first = self.cluster_environment.node_rank() * self.num_processes

        def command(local_rank: int) -> tuple[list[str], str]:
            return child_command(first + local_rank, self._pins.pinned)

        with mock.patch.object(subprocess_script, "_hydra_subprocess_cmd", command):
            super()._call_children_scripts()


class GradientAveraging(DDPStrategy):
    """Lightning's DDP strategy (one process per device, ranks started by Lightning) without
    torch's ``DistributedDataParallel`` wrapper, which cannot follow nrt's stages: stage 2
    resizes its grids mid-run, backpropagates several objectives a step and leaves the
    medium without gradient during its warm-up. Instead every rank starts from rank 0's
    parameters and buffers, and before each optimizer step every gradient becomes its mean
    over the ranks (:func:`average_gradients`), after the step's backward passes and before
    gradient clipping and the non-finite guard. Takes DDPStrategy's arguments
    (``process_group_backend: gloo`` on the CPU)."""

    def __init__(self, **kwargs) -> None:
        super().__init__(**kwargs)
        self.pinned: dict[str, object] = {}

    def pin(self, **overrides: object) -> None:
        """Overrides that ranks > 0 start with (``resume``, ``init.ea_ckpt``, ``threads``:
        rank 0's answers; a string, a number); None values are left out."""
        self.pinned.update({k: v for k, v in overrides.items() if v is not None})

    def _configure_launcher(self) -> None:
        if self._start_method != "popen":
            super()._configure_launcher()
            return
        self._launcher = _RankProcesses(self, self.cluster_environment, self.num_processes,
                                        self.num_nodes)

    def configure_ddp(self) -> None:
        """No wrapper: the module stays as it is, set to rank 0's state on every rank."""
        broadcast_state(self.model)

    def optimizer_step(self, optimizer, closure, model=None, **kwargs):
        """The step of ``optimizer`` with its parameters' gradients averaged over the ranks
        once the closure (automatic optimisation: the step's forward and backward) ran."""
        def closure_then_average():
            result = closure()
            average_gradients(p for group in optimizer.param_groups for p in group["params"])
            return result

        return super().optimizer_step(optimizer, closure_then_average, model, **kwargs)


def pin_for_ranks(trainer, **overrides: object) -> None:
    """Hand rank 0's decisions (:meth:`GradientAveraging.pin`) to the ranks the trainer will
    start; nothing for a trainer of one process."""
    if isinstance(trainer.strategy, GradientAveraging):
        trainer.strategy.pin(**overrides)


def parameters_digest(module: torch.nn.Module) -> str:
    """SHA-1 of a module's parameters (by name, as stored): equal on ranks in step."""
    digest = hashlib.sha1()
    for name, p in sorted(module.named_parameters()):
        digest.update(name.encode())
        digest.update(p.detach().cpu().contiguous().numpy().tobytes())
    return digest.hexdigest()


def rank_records(trainer, module: torch.nn.Module) -> list[dict]:
    """Every rank's record, by rank: host, pid, device, torch threads, steps taken and
    :func:`parameters_digest`. Every rank must call it (it gathers); one entry for a
    one-process run."""
    own = {"rank": trainer.global_rank, "host": socket.gethostname(), "pid": os.getpid(),
           "device": str(trainer.strategy.root_device), "threads": torch.get_num_threads(),
           "global_step": trainer.global_step, "parameters_sha1": parameters_digest(module)}
    if not (dist.is_available() and dist.is_initialized()) or dist.get_world_size() == 1:
        return [own]
    gathered: list[dict | None] = [None] * dist.get_world_size()
    dist.all_gather_object(gathered, own)
    return gathered


@contextmanager
def training_processes() -> Iterator[None]:
    """Around ``trainer.fit`` and what the ranks do together after it: on the way out, the
    process group is closed and the variables that launching the ranks put into this
    process's environment are put back, so that the next job of a sweep that runs in this
    process starts ranks of its own."""
    saved = {key: os.environ.get(key) for key in LAUNCH_VARIABLES}
    try:
        yield
    finally:
        if dist.is_available() and dist.is_initialized():
            dist.destroy_process_group()
        for key, value in saved.items():
            if value is None:
                os.environ.pop(key, None)
            else:
                os.environ[key] = value
