"""Grids that double during training (coarse to fine), shared by the voxel stages.

A schedule ``resolutions = [r0, r1, ...]`` with ``upsample_at = [f1, f2, ...]`` holds
``r_k`` from the run's progress ``f_k`` on (progress in [0, 1], of the steps or of the
time budget). When a grid parameter is resampled, Adam's moments for it restart. Measured
on stage 2 (cpu preset, default scene, 600 steps, grids 4 -> 8 -> 16 -> 32): moments
resampled with the grid left sigma_t's MSE x100 at 23.3 (each child cell sees 1/8 of its
parent's gradient, so the copied second moment kept Adam's steps 8x too small for hundreds
of steps); resampled and rescaled to the children's gradients, 13.3; restarted, 9.4 (the
first steps after a doubling move every cell by about the learning rate, downhill).
"""

from __future__ import annotations

from collections.abc import Callable

import torch

from nrt.errors import NrtError
from nrt.physics.volume import resample_cells


def check_schedule(resolutions: list[int], upsample_at: list[float], key: str) -> None:
    """One fraction per doubling, increasing, in (0, 1); resolutions positive."""
    if len(upsample_at) != len(resolutions) - 1 or any(r < 1 for r in resolutions) or \
            any(not 0 < f < 1 for f in upsample_at) or list(upsample_at) != sorted(upsample_at):
        raise NrtError(f"{key}: resolutions {list(resolutions)} need one increasing fraction "
                       f"of the run in (0, 1) per change, got upsample_at {list(upsample_at)}.")


def resolution_at(progress: float, resolutions: list[int], upsample_at: list[float]) -> int:
    """The scheduled resolution at ``progress`` in [0, 1]."""
    return int(resolutions[sum(progress >= f for f in upsample_at)])


@torch.no_grad()
def resample_parameter(param: torch.nn.Parameter, optimizer: torch.optim.Optimizer | None,
                       resolution: int) -> None:
    """Resample a grid parameter (R, R, R, C) to ``resolution``^3 cells (trilinear,
    cell-centred) and restart its optimizer state."""
    if optimizer is not None:
        optimizer.state.pop(param, None)
    param.data = resample_cells(param.data, resolution)


def decaying_lr(optimizer: torch.optim.Optimizer, final_factor: float,
                progress: Callable[[], float], ramp: Callable[[], float] | None = None
                ) -> torch.optim.lr_scheduler.LambdaLR:
    """Every group's learning rate times ``final_factor ** progress()``: an exponential decay
    over the run's steps or its ``budget_s`` (stepped once per training step). A constant
    rate leaves the voxel grids walking in their gradients' noise at the end of a run.
    With ``ramp``, the groups marked ``ramps_in`` also take ``ramp()`` (in [0, 1]) as a
    factor (:func:`ramp_in`)."""
    def decay(_: int) -> float:
        return final_factor ** progress()

    if ramp is None:
        return torch.optim.lr_scheduler.LambdaLR(optimizer, decay)

    def ramped(step: int) -> float:
        return decay(step) * ramp()
    return torch.optim.lr_scheduler.LambdaLR(
        optimizer, [ramped if group.get("ramps_in") else decay
                    for group in optimizer.param_groups])


def ramp_in(progress: float, start: float, length: float) -> float:
    """A linear ramp from 0 at ``start`` to 1 at ``start + length`` (shares of the run):
    Adam's first steps on freshly started moments move every coordinate by about the
    learning rate, whatever the gradient's size; a ramp lets the moments settle first.
    ``length`` 0: 1 from ``start`` on."""
    if progress < start:
        return 0.0
    return 1.0 if length <= 0 else min(1.0, (progress - start) / length)
