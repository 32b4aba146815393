"""Lightning callbacks shared by every stage."""

from __future__ import annotations

import io
import logging
import random
import time
from pathlib import Path

import lightning as L
import torch
import torch.distributed as dist
from lightning.fabric.plugins.io.torch_io import TorchCheckpointIO
from lightning.pytorch.callbacks import ModelCheckpoint

from nrt.compile import missing_compiler, use_cache
from nrt.distributed import rank_seed
from nrt.errors import ConfigError
from nrt.files import TEMP_MARK, atomic_write, writing
from nrt.physics.fused_lookup import fused_lookups, use_fused_lookups
from nrt.stages.schedules import RunClock
from nrt.stages.stage import Stage

log = logging.getLogger(__name__)


class WallClock(L.Callback, RunClock):
    """Logs ``time/wall_s``, training seconds since the run started, next to the metrics;
    with ``budget_s``, stops training once that many seconds are spent (equal-time runs).

    Validation is not counted (the clock pauses while it runs), so accuracy-versus-time
    curves and budgets measure optimisation alone, whatever the validation cadence. The
    elapsed time is stored in checkpoints: a resumed run continues its clock and budget.
    Schedules over the run's course read it
    (:func:`~nrt.stages.schedules.training_progress`). In a run of several processes with a
    budget, every rank reads rank 0's clock as it was at the end of the last step
    (:meth:`schedule_seconds`) and stops when it is spent, so that the ranks double their
    grids and stop at the same step.
    """

    def __init__(self, budget_s: float | None = None):
        if budget_s is not None and budget_s <= 0:
            raise ConfigError(f"budget_s must be a positive number of seconds (or null), got "
                              f"{budget_s}.")
        self.budget_s = budget_s
        self.elapsed_before = 0.0
        self._start: float | None = None
        self._agreed: float | None = None  # rank 0's seconds, with a budget and several ranks

    def seconds(self) -> float:
        running = 0.0 if self._start is None else time.perf_counter() - self._start
        return self.elapsed_before + running

    def pause(self) -> None:
        """Stop counting (validation, measurements kept outside the budget)."""
        if self._start is not None:
            self.elapsed_before, self._start = self.seconds(), None

    def resume(self) -> None:
        """Count again after :meth:`pause`."""
        if self._start is None:
            self._start = time.perf_counter()

    def schedule_seconds(self) -> float:
        """The seconds that schedules and the budget go by: :meth:`seconds`, or rank 0's at
        the end of the last step in a run of several processes with a budget."""
        return self.seconds() if self._agreed is None else self._agreed

    def on_train_start(self, trainer, pl_module) -> None:
        self.resume()
        if self.budget_s is not None and getattr(trainer, "world_size", 1) > 1:
            self._agreed = self.elapsed_before  # the checkpoint's, the same on every rank

    def on_train_end(self, trainer, pl_module) -> None:
        self.pause()

    def on_validation_start(self, trainer, pl_module) -> None:
        self.pause()

    def on_validation_end(self, trainer, pl_module) -> None:
        if not trainer.sanity_checking and trainer.state.fn == "fit":
            self.resume()

    def on_train_batch_end(self, trainer, pl_module, outputs, batch, batch_idx) -> None:
        seconds = self.seconds()
        pl_module.log("time/wall_s", seconds)
        if self._agreed is not None:
            self._agreed = seconds = float(trainer.strategy.broadcast(seconds))
        if self.budget_s is not None and seconds >= self.budget_s and not trainer.should_stop:
            log.info("Time budget of %.0f s spent at step %d: stopping.", self.budget_s,
                     trainer.global_step)
            trainer.should_stop = True

    def on_validation_epoch_end(self, trainer, pl_module) -> None:
        if not trainer.sanity_checking:
            pl_module.log("time/wall_s", self.seconds())

    def state_dict(self) -> dict:
        return {"elapsed": self.seconds()}

    def load_state_dict(self, state_dict: dict) -> None:
        self.elapsed_before = float(state_dict.get("elapsed", 0.0))


def all_finite(t: torch.Tensor) -> bool:
    """Whether ``t`` holds no NaN or Inf: its sum is finite (one pass, no mask), or, where
    the sum overflows, every entry is."""
    return bool(torch.isfinite(t.sum())) or bool(torch.isfinite(t).all())


class NonFiniteGuard(L.Callback):
    """Keeps NaN and Inf out of the parameters.

    Non-finite gradient entries are zeroed before each optimizer step (and counted in
    ``guard/nonfinite_grads``); a parameter that still turns non-finite stops training
    with an error naming it. A tensor whose sum is finite holds no NaN or Inf (either would
    make the sum NaN or infinite), so one reduction without a mask clears it; only a sum
    that is not finite (such entries, or finite ones that overflow) is looked at entry by
    entry.
    """

    def on_before_optimizer_step(self, trainer, pl_module, optimizer) -> None:
        bad = 0
        for p in pl_module.parameters():
            if p.grad is not None and not all_finite(p.grad):
                mask = ~torch.isfinite(p.grad)
                if mask.any():
                    bad += int(mask.sum())
                    p.grad[mask] = 0.0
        if bad:
            log.warning("zeroed %d non-finite gradient entries at step %d", bad,
                        trainer.global_step)
        pl_module.log("guard/nonfinite_grads", float(bad))

    def on_train_batch_end(self, trainer, pl_module, outputs, batch, batch_idx) -> None:
        for name, p in pl_module.named_parameters():
            if not all_finite(p.detach()):
                raise FloatingPointError(f"parameter '{name}' became non-finite at step "
                                         f"{trainer.global_step}")


class HeldOutImageMetrics(L.Callback):
    """PSNR, SSIM (and optionally LPIPS) of every held-out view a stage renders.

    A stage's ``validation_step`` returns ``{"image": pred, "reference": ref}``, both
    (H, W, 3) linear radiance; this logs ``val/psnr``, ``val/ssim`` (and ``val/lpips``),
    averaged over the views, next to ``time/wall_s``. A view of a family member (the output
    holds ``member`` k) is also logged as ``val/<metric>_member<k>``, averaged over that
    member's views; with the same number of views per member, ``val/<metric>`` is then the
    mean over members.
    """

    def __init__(self, lpips: bool = False, lpips_net: str = "alex"):
        self.lpips_enabled, self.lpips_net = lpips, lpips_net
        self._lpips = None
        if lpips:  # missing weights are refused before nrt-train loads any data
            from nrt.weights import lpips_backbone_path

            lpips_backbone_path(lpips_net)

    def setup(self, trainer, pl_module, stage: str) -> None:
        if self.lpips_enabled and self._lpips is None:
            from nrt.metrics import LPIPS

            self._lpips = LPIPS(self.lpips_net)  # fails early when the weights are missing

    def on_validation_batch_end(self, trainer, pl_module, outputs, batch, batch_idx,
                                dataloader_idx: int = 0) -> None:
        if not isinstance(outputs, dict) or "image" not in outputs:
            return
        from nrt.metrics import psnr, ssim

        pred, ref = outputs["image"].detach(), outputs["reference"].detach()
        scores = {"psnr": psnr(pred, ref), "ssim": ssim(pred, ref)}
        if self._lpips is not None:
            scores["lpips"] = self._lpips(pred.cpu(), ref.cpu())
        member = outputs.get("member")
        for name, value in scores.items():
            pl_module.log(f"val/{name}", value, batch_size=1)
            if member is not None:
                pl_module.log(f"val/{name}_member{member}", value, batch_size=1)


class PropertyMetrics(L.Callback):
    """Medium-property MSE x 10^2 against the truth (docs/conventions.md, "Property metrics").

    For a stage that learns a medium (:meth:`nrt.stages.stage.Stage.property_grids` is not
    None) and a dataset with ``ground_truth.npz``: ``val/mse_{sigma_a,sigma_s,sigma_t}_x100``
    and, where the stage learns g (:attr:`~nrt.stages.stage.Stage.learns_g`: not for an
    isotropic scene or a fixed g), ``val/mse_g_x100`` (weighted by the true sigma_s), at
    step 0 (the starting point of accuracy-versus-time curves), after each validation and
    when training ends; with ``slices``, the middle z-slices learned | true to TensorBoard.
    With ``every_s``, also each time another ``every_s`` training seconds have passed
    (curves with points at fixed wall-clock intervals, whatever the step rate): the
    training clock (:class:`WallClock`) is paused while it measures, so the measurement
    counts in no method's time or budget. In a run of several processes rank 0 alone
    measures (the ranks hold the same medium).

    On a scene family, for a stage with a medium per member
    (:meth:`~nrt.stages.stage.Stage.member_property_grids`): each member's MSEs against its
    own ground truth, ``val/mse_<property>_x100_member<k>``, and their mean
    ``val/mse_<property>_x100`` (slices of member 0).
    """

    def __init__(self, slices: bool = True, every_s: float | None = None):
        if every_s is not None and every_s <= 0:
            raise ConfigError(f"callbacks.property_metrics.every_s={every_s}: a positive "
                              "number of training seconds between measurements, or null.")
        self.slices, self.every_s = slices, every_s
        self._last_measured: int | None = None
        self._next_due = every_s

    def measure(self, trainer, pl_module: Stage) -> dict[str, float]:
        gt = pl_module.ground_truth()
        if gt is None:
            return self.measure_members(trainer, pl_module)
        return self.score(pl_module, pl_module.property_grids(gt["g"].shape[0]), gt,
                          self.slices)

    def score(self, pl_module: Stage, learned: dict | None, gt: dict,
              slices: bool) -> dict[str, float]:
        """``val/mse_<property>_x100`` of ``learned`` grids against ``gt`` ({} without
        grids)."""
        if learned is None:
            return {}
        from nrt.metrics import property_mse

        truth = {k: v.to(learned["sigma_a"].device) for k, v in gt.items()}
        with_g = pl_module.learns_g
        if slices:
            self._log_slices(pl_module, learned, truth, with_g)
        return {f"val/mse_{k}_x100": float(v)
                for k, v in property_mse(learned, truth, with_g).items()}

    def measure_members(self, trainer, pl_module: Stage) -> dict[str, float]:
        """Per-member scores and their means on a family (members without ground truth
        are left out); {} for anything else."""
        truths = getattr(trainer.datamodule, "member_ground_truths", None) or []
        per_member: dict[str, list[float]] = {}
        out = {}
        for k, gt in enumerate(truths):
            if gt is None:
                continue
            learned = pl_module.member_property_grids(k, gt["g"].shape[0])
            for key, value in self.score(pl_module, learned, gt,
                                         self.slices and not per_member).items():
                out[f"{key}_member{k}"] = value
                per_member.setdefault(key, []).append(value)
        out.update({key: sum(v) / len(v) for key, v in per_member.items()})
        return out

    @staticmethod
    def _log_slices(pl_module, learned: dict, truth: dict, with_g: bool) -> None:
        from nrt.tensorboard import log_image

        mid = truth["sigma_a"].shape[0] // 2
        for key in ("sigma_a", "sigma_s"):
            panel = torch.cat((learned[key][mid], truth[key][mid]), 1)
            log_image(pl_module, f"val/{key}_slice_vs_truth", panel, tonemap=False)
        if with_g:
            g = torch.cat((learned["g"][mid], truth["g"][mid]), 1)
            log_image(pl_module, "val/g_slice_vs_truth",
                      ((g + 1) / 2).unsqueeze(-1).expand(-1, -1, 3), tonemap=False)

    def _log_direct(self, trainer, pl_module, slices: bool = True) -> None:
        """Outside a validation loop: straight to the loggers, with the clock beside."""
        if not _lead(trainer):
            return
        clock = next((c for c in trainer.callbacks if isinstance(c, WallClock)), None)
        seconds = clock.seconds() if clock is not None else None  # before measuring
        keep, self.slices = self.slices, self.slices and slices
        try:
            values = self.measure(trainer, pl_module)
        finally:
            self.slices = keep
        if not values:
            return
        if seconds is not None:
            values["time/wall_s"] = seconds
        for logger in trainer.loggers:
            logger.log_metrics(values, step=trainer.global_step)
            logger.save()

    def on_train_start(self, trainer, pl_module) -> None:
        if trainer.global_step == 0:
            self._log_direct(trainer, pl_module)

    def on_train_batch_end(self, trainer, pl_module, outputs, batch, batch_idx) -> None:
        if self.every_s is None or not _lead(trainer):
            return
        clock = next((c for c in trainer.callbacks if isinstance(c, WallClock)), None)
        if clock is None or clock.seconds() < self._next_due:
            return
        clock.pause()
        try:
            self._log_direct(trainer, pl_module, slices=False)
            self._last_measured = trainer.global_step
        finally:
            clock.resume()
        while self._next_due <= clock.seconds():
            self._next_due += self.every_s

    def on_validation_epoch_end(self, trainer, pl_module) -> None:
        if trainer.sanity_checking:
            return
        self._last_measured = trainer.global_step
        if not _lead(trainer):
            return
        for key, value in self.measure(trainer, pl_module).items():
            pl_module.log(key, value, rank_zero_only=True)

    def on_train_end(self, trainer, pl_module) -> None:
        if self._last_measured != trainer.global_step:
            self._log_direct(trainer, pl_module)


class RerenderEvaluation(L.Callback):
    """Periodic ``nrt-eval``-style re-render during training (off when
    ``every_n_validations`` is 0): every n-th validation, the current medium is rendered
    with Mitsuba for ``max_views`` held-out views per environment (``novel``: those not
    trained on) at ``spp``, and ``eval/psnr_<group>``, ``eval/ssim_<group>`` are logged
    next to ``time/wall_s``. Costs one Mitsuba render per view; the clock is paused. Rank 0
    alone renders in a run of several processes."""

    def __init__(self, every_n_validations: int = 0, spp: int = 16, max_views: int = 2,
                 environments: str | list = "novel", resolution: int | None = None):
        self.every, self.spp, self.max_views = every_n_validations, spp, max_views
        self.environments, self.resolution = environments, resolution
        self._count = 0
        self._data = None

    def on_validation_epoch_end(self, trainer, pl_module: Stage) -> None:
        if self.every <= 0 or trainer.sanity_checking or not _lead(trainer):
            return
        self._count += 1
        if self._count % self.every:
            return
        grids = pl_module.property_grids(pl_module.grid_resolution(self.resolution or None, 64))
        if grids is None:  # a stage without a medium
            return
        from nrt.data.dataset import load_dataset
        from nrt.evaluation.evaluate import Evaluation, rerender_metrics

        dm = trainer.datamodule
        if self._data is None:
            self._data = load_dataset(dm.dataset_dir, "test")
        result = Evaluation()
        settings = {"environments": self.environments, "max_views": self.max_views,
                    "spp": self.spp, "noise_floor": False}
        rerender_metrics(grids, pl_module.effects, self._data,
                         dm.train_data.environments_used(), settings, None, result)
        for key, value in result.metrics.items():
            if key.startswith(("psnr_", "ssim_")) and "_env_" not in key:
                pl_module.log(f"eval/{key}", value, rank_zero_only=True)


class AtomicCheckpointIO(TorchCheckpointIO):
    """Writes each checkpoint to a temporary file beside it, flushed to disk and renamed
    over the old one (:func:`nrt.files.atomic_write`): a process killed or a disk filled
    while ``last.ckpt`` is written leaves the previous ``last.ckpt`` whole, which
    ``resume=true`` continues from (and the next save removes the killed write's temporary
    file). A failed write is a :class:`~nrt.errors.WriteError` naming the checkpoint."""

    def save_checkpoint(self, checkpoint: dict, path, storage_options=None) -> None:
        path = Path(path)
        left = (f"every checkpoint saved before it in '{path.parent}' is whole: once there "
                "is space, the same command with resume=true continues from last.ckpt")
        with writing("the checkpoint", path, left):
            path.parent.mkdir(parents=True, exist_ok=True)
            for stale in path.parent.glob(f".{path.name}{TEMP_MARK}*"):  # of a killed run
                stale.unlink(missing_ok=True)
        buffer = io.BytesIO()  # serialised first: a failed write then raises OSError itself
        torch.save(checkpoint, buffer)
        with atomic_write(path, "the checkpoint", left=left) as f:
            f.write(buffer.getbuffer())


class RandomState(L.Callback):
    """Keeps the global random generators (torch's and Python's; nrt draws nothing from
    NumPy's global one) in each checkpoint and puts them back when a resumed run starts
    training, so that it draws the numbers the run left alone would have drawn (the ray
    batches follow generators of their own: :meth:`nrt.data.datamodule.RandomRays.resume_at`).

    In a run of several processes each rank draws its own Monte Carlo samples: a new run's
    rank r > 0 seeds its generators with :func:`nrt.distributed.rank_seed` of ``seed`` when
    training starts (rank 0 keeps the run's), and a checkpoint keeps every rank's
    generators (``ranks``, gathered as the ranks save it together) for each to take back;
    a checkpoint of another number of processes gives rank 0 its own and seeds the rest."""

    def __init__(self, seed: int | None = None) -> None:
        self.seed = seed
        self._loaded: dict | None = None

    @staticmethod
    def _own() -> dict:
        return {"torch": torch.get_rng_state(),
                "cuda": torch.cuda.get_rng_state_all() if torch.cuda.is_available() else [],
                "python": random.getstate()}

    def state_dict(self) -> dict:
        """This process's generators; with several processes also every rank's."""
        state = self._own()
        if dist.is_available() and dist.is_initialized() and dist.get_world_size() > 1:
            ranks: list[dict | None] = [None] * dist.get_world_size()
            dist.all_gather_object(ranks, state)
            state["ranks"] = ranks
        return state

    def load_state_dict(self, state_dict: dict) -> None:
        self._loaded = state_dict

    def on_train_start(self, trainer, pl_module) -> None:
        rank, world = getattr(trainer, "global_rank", 0), getattr(trainer, "world_size", 1)
        state, self._loaded = self._loaded, None
        if state is not None and len(state.get("ranks") or []) == world:
            state = state["ranks"][rank]
        elif rank > 0:
            state = None
        if state is None:
            if rank > 0:
                seed = rank_seed(self.seed if self.seed is not None else 0, rank)
                torch.manual_seed(seed)
                random.seed(seed)
            return
        torch.set_rng_state(state["torch"])
        if state["cuda"] and torch.cuda.is_available():
            torch.cuda.set_rng_state_all(state["cuda"])
        random.setstate(state["python"])


class CompileHotCode(L.Callback):
    """With ``enabled`` (``compile=true``), compiles the stage's hot code
    (:meth:`~nrt.stages.stage.Stage.compile_hot_code`) before training, its kernels cached
    under ``cache_dir``; where no compiler is present, a warning and eager code
    (:mod:`nrt.compile`). Logs ``time/first_step_s``, the first training step's seconds in
    this process, which hold the compilation."""

    def __init__(self, enabled: bool = False, cache_dir: str | None = None):
        self.enabled, self.cache_dir = bool(enabled), cache_dir
        self.compiled = False
        self._first_start: float | None = None

    def setup(self, trainer, pl_module, stage: str) -> None:
        if not self.enabled or stage != "fit" or self.compiled:
            return
        missing = missing_compiler(trainer.strategy.root_device.type)
        if missing is not None:
            log.warning("compile=true, but %s: the run trains with eager code", missing)
            return
        use_cache(self.cache_dir)
        pl_module.compile_hot_code()
        self.compiled = True

    def on_train_batch_start(self, trainer, pl_module, batch, batch_idx) -> None:
        if self._first_start is None:
            self._first_start = time.perf_counter()

    def on_train_batch_end(self, trainer, pl_module, outputs, batch, batch_idx) -> None:
        if self._first_start is not None and self._first_start > 0:
            pl_module.log("time/first_step_s", time.perf_counter() - self._first_start)
            self._first_start = -1.0


class FusedLookups(L.Callback):
    """With ``enabled`` (``fused_lookups=true``), the grid lookups of the run
    (:func:`~nrt.physics.volume.sample_grid`) and of the environment maps take the fused CPU
    kernels where they apply (:mod:`nrt.physics.fused_lookup`: the same values, the grid's
    gradient summed in another order; :mod:`nrt.physics.fused_envmap`), from setup to
    teardown (or an error)."""

    def __init__(self, enabled: bool = False):
        self.enabled = bool(enabled)
        self._before: bool | None = None

    def setup(self, trainer, pl_module, stage: str) -> None:
        if self._before is None:
            self._before = fused_lookups()
            use_fused_lookups(self.enabled)

    def teardown(self, trainer, pl_module, stage: str) -> None:
        if self._before is not None:
            use_fused_lookups(self._before)
            self._before = None

    def on_exception(self, trainer, pl_module, exception: BaseException) -> None:
        self.teardown(trainer, pl_module, "fit")  # Lightning skips teardown after an error


class PeakMemory(L.Callback):
    """The process's peak memory every ``every_n_steps`` training steps, rank 0's:
    ``memory/peak_rss_gib``, the most resident memory it has held (``getrusage``; Linux
    counts KiB), and on a GPU ``memory/peak_cuda_gib`` (``torch.cuda.max_memory_allocated``).
    Not in the default callbacks: ``'+callbacks.peak_memory={_target_:nrt.callbacks.PeakMemory}'``
    adds it (``benchmarks/gpu_smoke.py``)."""

    def __init__(self, every_n_steps: int = 1):
        self.every = max(1, int(every_n_steps))

    def on_train_batch_end(self, trainer, pl_module, outputs, batch, batch_idx) -> None:
        if trainer.global_step % self.every == 0:
            for key, value in peak_memory(pl_module.device).items():
                pl_module.log(key, value)


def peak_memory(device: torch.device) -> dict[str, float]:
    """:class:`PeakMemory`'s values for this process, in GiB."""
    import resource

    out = {"memory/peak_rss_gib": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2**20}
    if device.type == "cuda":
        out["memory/peak_cuda_gib"] = torch.cuda.max_memory_allocated(device) / 2**30
    return out


def _lead(trainer) -> bool:
    """Whether this process measures for the run: rank 0, or the only process."""
    return getattr(trainer, "is_global_zero", True)


class LastCheckpoint(ModelCheckpoint):
    """``checkpoints/last.ckpt`` every ``every_n_train_steps`` steps; a step that validation
    follows (the last of an epoch) is saved once validation has ended, so that the
    checkpoint holds the random generators as the run goes on from it (validation draws
    from them too) and a run resumed from it continues exactly (:class:`RandomState`).
    Give it ``save_on_train_epoch_end: false``."""

    def on_train_batch_end(self, trainer, pl_module, outputs, batch, batch_idx) -> None:
        due = self._every_n_train_steps >= 1 and \
            trainer.global_step % self._every_n_train_steps == 0
        if due and _validates_next(trainer):
            self._defer_save_until_validation = True  # ModelCheckpoint saves at validation end
            return
        super().on_train_batch_end(trainer, pl_module, outputs, batch, batch_idx)

    def on_train_end(self, trainer, pl_module) -> None:
        """The end of training is always in ``last.ckpt`` (a deferred save whose validation
        did not come, or a run shorter than ``every_n_train_steps``)."""
        self._defer_save_until_validation = False
        if self._last_global_step_saved != trainer.global_step:
            self._save_last_checkpoint(trainer, self._monitor_candidates(trainer))


def _validates_next(trainer) -> bool:
    """Whether validation runs after the batch just trained on: the last of an epoch that
    validates (as Lightning's own ModelCheckpoint tells it)."""
    every = trainer.check_val_every_n_epoch or 1
    last = getattr(trainer.fit_loop.epoch_loop.batch_progress, "is_last_batch", False)
    return bool(trainer.enable_validation) and last and (trainer.current_epoch + 1) % every == 0
