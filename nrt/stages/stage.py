"""The stage contract: what every stage of nrt (a LightningModule that ``nrt-train
stage=<name>`` trains) provides, so that callbacks, evaluation and the CLI rely on it
instead of probing.

Every stage implements Lightning's ``training_step`` and ``configure_optimizers``, and a
``validation_step`` that returns ``{"image": pred, "reference": ref}``, both (H, W, 3)
linear radiance of one held-out view (:class:`nrt.callbacks.HeldOutImageMetrics` scores
them). It gets the dataset from the trainer's datamodule
(:class:`nrt.data.datamodule.RayDataModule`) through :meth:`Stage.datamodule`.

Optional, with these defaults:

- ``effects``: the scene's declared effects (``scene.effects``); ``{}`` for a stage that
  reads none.
- :meth:`Stage.property_grids`: the learned medium on the ground truth's grid layout
  (what the property metrics, the periodic re-render and ``nrt-eval`` score); None for a
  stage that learns none.
- :meth:`Stage.medium_bbox`: the box those grids cover; None without them.
- :meth:`Stage.member_property_grids`: a family member's learned medium, for a stage
  trained on a scene family (``mode=generative``); None otherwise.
- :attr:`Stage.learns_g`: whether g is a learned property that metrics should score
  (default: whenever the scene's phase has a g).
- :attr:`Stage.voxel_media`: whether the stage learns voxel media, which priors on voxels
  read (:class:`~nrt.losses.context.StepContext`'s ``voxels``); False.
- :meth:`Stage.export`: files written into the run folder after training; none.
- :meth:`Stage.compile_hot_code`: what ``compile=true`` compiles in place before training
  (:mod:`nrt.compile`); nothing.

Every checkpoint a stage saves records nrt's checkpoint format, and a resume from one of
another format, or whose config groups the optimiser otherwise, is refused
(:mod:`nrt.stages.checkpoints`); a subclass that overrides ``on_save_checkpoint``,
``on_load_checkpoint`` or ``on_fit_start`` calls the base's.

Shared helpers: :meth:`Stage.ground_truth`, :meth:`Stage.progress` (of the run's steps or
time budget, for schedules), :meth:`Stage.grid_resolution` and :meth:`Stage.view_baselines`
(the PSNRs a held-out view's validation logs beside the stage's own, extended through
:meth:`Stage.more_baselines`). A stage checks its config
when it is built (:class:`~nrt.errors.ConfigError`, e.g. :func:`check_learning_rates`), so
that nrt-train refuses mistakes before it loads any data.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import lightning as L
import torch
from torch.profiler import record_function

from nrt.distributed import synced
from nrt.errors import ConfigError
from nrt.metrics import psnr
from nrt.stages.checkpoints import check_format, check_optimizer_layout, optimizer_layout, stamp
from nrt.stages.schedules import training_progress


def check_learning_rates(lr: float | dict[str, float], key: str,
                         parts: tuple[str, ...] | None = None) -> None:
    """Refuse learning rates that are not positive numbers; ``key`` names them in the
    message (``model.lr``). ``parts``: the rate is a mapping that must give each of these
    (one per parameter group, e.g. ``light``, ``medium``); None: one number."""
    if parts is not None:
        missing = [p for p in parts if not isinstance(lr, dict) or p not in lr]
        if missing:
            raise ConfigError(f"{key}={lr}: this stage takes one learning rate per part, "
                              f"{', '.join(parts)}; {', '.join(missing)} missing. Set each: "
                              + " ".join(f"{key}.{p}=<rate>" for p in parts) + ".")
    elif isinstance(lr, dict):
        raise ConfigError(f"{key}={lr}: this stage takes one learning rate, a positive number "
                          f"({key}=0.01), not a mapping.")
    for name, rate in (lr.items() if isinstance(lr, dict) else [("", lr)]):
        if isinstance(rate, bool) or not isinstance(rate, int | float) or rate <= 0:
            raise ConfigError(f"{key}{'.' + name if name else ''}={rate}: a learning rate must "
                              "be a positive number.")


class Stage(L.LightningModule):
    """Base of every stage; see the module's docstring for the contract."""

    voxel_media: bool = False
    """Whether the stage learns voxel media (the objectives' ``StepContext.voxels``)."""

    def __init__(self, effects: dict | None = None):
        super().__init__()
        self.effects = effects if effects is not None else {}
        self._baselines: dict[tuple[int | None, int], dict[str, float]] = {}

    # ------------------------------------------------------------ what stages offer
    def property_grids(self, resolution: int) -> dict[str, torch.Tensor] | None:
        """The learned medium at resolution^3 cells, ``[z, y, x]``-indexed like the dataset's
        ground truth: ``sigma_a``, ``sigma_s`` (R, R, R, 3) and ``g`` (R, R, R); None for a
        stage that learns no medium."""
        return None

    def member_property_grids(self, member: int, resolution: int
                              ) -> dict[str, torch.Tensor] | None:
        """Member ``member``'s learned medium in the layout of :meth:`property_grids`, for
        a stage trained on a scene family; None for a stage without one medium a member."""
        return None

    def medium_bbox(self) -> torch.Tensor | None:
        """The box (2, 3) that :meth:`property_grids` covers; None without a medium."""
        return None

    @property
    def learns_g(self) -> bool:
        """Whether metrics score g among the learned properties (when there are any):
        whenever the scene's phase has a g; a stage that keeps g fixed says False."""
        return self.effects.get("phase", "hg") != "isotropic"

    def export(self, run_dir: str | Path) -> dict[str, str]:
        """Write what the run produced into ``run_dir`` after training; name -> path."""
        return {}

    def compile_hot_code(self) -> None:
        """``torch.compile`` the code that dominates a training step, in place (``compile=true``,
        :class:`nrt.callbacks.CompileHotCode`; :mod:`nrt.compile`): none here."""

    # ------------------------------------------------------------- checkpoints
    def on_save_checkpoint(self, checkpoint: dict) -> None:
        """Record the checkpoint format (:func:`~nrt.stages.checkpoints.stamp`)."""
        stamp(checkpoint)

    def on_load_checkpoint(self, checkpoint: dict) -> None:
        """Refuse a checkpoint of another format (:func:`~nrt.stages.checkpoints.check_format`)
        and keep its optimisers' layout for :meth:`on_fit_start`."""
        check_format(checkpoint, "the checkpoint to resume from")
        self._saved_optimizer_layout = [optimizer_layout(state["param_groups"])
                                        for state in checkpoint.get("optimizer_states", [])]

    def on_fit_start(self) -> None:
        """On a resume, refuse optimisers grouped otherwise than the checkpoint's
        (:func:`~nrt.stages.checkpoints.check_optimizer_layout`): Lightning configures them
        after :meth:`on_load_checkpoint` and loads their state after this hook."""
        saved = self.__dict__.pop("_saved_optimizer_layout", None)
        if saved:
            check_optimizer_layout(saved, [optimizer_layout(opt.param_groups)
                                           for opt in self.trainer.optimizers],
                                   self.trainer.ckpt_path or "the checkpoint to resume from")

    # ------------------------------------------------------------------ helpers
    def view_baselines(self, batch: dict) -> dict[str, float]:
        """PSNRs (dB) of predictions a learned medium should beat, for one held-out view
        (``rgb``, ``background``, ``view``, optional ``member``), computed once per (member,
        view): ``psnr_background_only`` (no medium: the background alone) and what
        :meth:`more_baselines` adds. Validation logs each as ``val/<name>``."""
        view = (batch.get("member"), int(batch["view"]))
        if view not in self._baselines:
            self._baselines[view] = {
                "psnr_background_only": float(psnr(batch["background"], batch["rgb"])),
                **self.more_baselines(batch)}
        return self._baselines[view]

    def more_baselines(self, batch: dict) -> dict[str, float]:
        """Further baselines of :meth:`view_baselines` (name -> PSNR in dB); none here."""
        return {}

    def log(self, name: str, value, *args, **kwargs) -> None:
        """Lightning's ``log``, in the profiler scope ``nrt/logging`` (benchmarks.profile_step
        counts it as the framework's time). Every stage's and callback's metric passes
        here: in a run of several processes it is the mean over the ranks (``sync_dist``),
        unless it is a rank's own (:func:`nrt.distributed.synced`: clocks, timings,
        memory) or rank 0 logs it alone (``rank_zero_only=True``)."""
        if not kwargs.get("rank_zero_only") and synced(name):
            kwargs.setdefault("sync_dist", True)
        with record_function("nrt/logging"):
            super().log(name, value, *args, **kwargs)

    def datamodule(self):
        """The attached trainer's datamodule; None outside a trainer."""
        return self.trainer.datamodule if self._trainer is not None else None

    def ground_truth(self) -> dict[str, torch.Tensor] | None:
        """The dataset's ground-truth grids, when it has them and a trainer is attached."""
        dm = self.datamodule()
        return dm.ground_truth if dm is not None else None

    def progress(self) -> float:
        """How far the run is, in [0, 1] (:func:`~nrt.stages.schedules.training_progress`);
        0 outside a trainer."""
        return training_progress(self.trainer) if self._trainer is not None else 0.0

    def grid_resolution(self, requested: int | None, fallback: int,
                        truths: Sequence[dict[str, torch.Tensor] | None] | None = None) -> int:
        """Cells per axis of exported or scored grids: ``requested``, else that of the first
        of ``truths`` (default: the dataset's ground truth; a family passes its members')
        that exists, else ``fallback``."""
        return grid_resolution(requested, fallback,
                               [self.ground_truth()] if truths is None else truths)


def grid_resolution(requested: int | None, fallback: int,
                    truths: Sequence[dict[str, torch.Tensor] | None]) -> int:
    """Cells per axis of exported or scored grids: ``requested``, else that of the first of
    ``truths`` (ground-truth grids) that exists, else ``fallback``."""
    if requested is not None:
        return int(requested)
    gt = next((t for t in truths if t is not None), None)
    return int(gt["g"].shape[0]) if gt is not None else int(fallback)
