"""Lightning callbacks shared by every stage."""

from __future__ import annotations

import logging
import time

import lightning as L
import torch

log = logging.getLogger(__name__)


class WallClock(L.Callback):
    """Logs ``time/wall_s``, training seconds since the run started, next to the metrics.

    The elapsed time is stored in checkpoints, so a resumed run continues its clock and
    accuracy-versus-time curves stay continuous across a kill and resume.
    """

    def __init__(self):
        self.elapsed_before = 0.0
        self._start: float | None = None

    def seconds(self) -> float:
        running = 0.0 if self._start is None else time.perf_counter() - self._start
        return self.elapsed_before + running

    def on_train_start(self, trainer, pl_module) -> None:
        self._start = time.perf_counter()

    def on_train_end(self, trainer, pl_module) -> None:
        self.elapsed_before, self._start = self.seconds(), None

    def on_train_batch_end(self, trainer, pl_module, outputs, batch, batch_idx) -> None:
        pl_module.log("time/wall_s", self.seconds())

    def on_validation_epoch_end(self, trainer, pl_module) -> None:
        if not trainer.sanity_checking:
            pl_module.log("time/wall_s", self.seconds())

    def state_dict(self) -> dict:
        return {"elapsed": self.seconds()}

    def load_state_dict(self, state_dict: dict) -> None:
        self.elapsed_before = float(state_dict.get("elapsed", 0.0))


class NonFiniteGuard(L.Callback):
    """Keeps NaN and Inf out of the parameters.

    Non-finite gradient entries are zeroed before each optimizer step (and counted in
    ``guard/nonfinite_grads``); a parameter that still turns non-finite stops training
    with an error naming it.
    """

    def on_before_optimizer_step(self, trainer, pl_module, optimizer) -> None:
        bad = 0
        for p in pl_module.parameters():
            if p.grad is not None:
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
            if not torch.isfinite(p).all():
                raise FloatingPointError(f"parameter '{name}' became non-finite at step "
                                         f"{trainer.global_step}")
