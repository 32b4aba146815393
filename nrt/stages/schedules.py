"""The run's progress in [0, 1] (of its steps, or of its time budget), read by the stages:
coarse-to-fine grids, warm-ups, learning-rate decays and objective weights
(:class:`nrt.losses.objective.WeightSchedule`) follow it."""

from __future__ import annotations


class RunClock:
    """A training clock among a trainer's callbacks, as :func:`training_progress` reads
    it: training seconds so far and the time budget (None: no limit).
    :class:`nrt.callbacks.WallClock` is the one nrt-train installs."""

    budget_s: float | None = None

    def seconds(self) -> float:
        """Training seconds so far."""
        raise NotImplementedError

    def schedule_seconds(self) -> float:
        """The training seconds that schedules go by: :meth:`seconds` (a clock shared by
        several processes gives the same answer on each)."""
        return self.seconds()


def training_progress(trainer) -> float:
    """How far a run is, in [0, 1]: the larger of steps / max_steps and, with a time budget
    (``budget_s``), training seconds / budget, so that schedules over a run's course
    (coarse to fine, warm-ups) also complete in equal-time runs."""
    done = trainer.global_step / max(int(trainer.max_steps), 1) if trainer.max_steps > 0 else 0.0
    clock = next((c for c in trainer.callbacks if isinstance(c, RunClock)), None)
    if clock is not None and clock.budget_s:
        done = max(done, clock.schedule_seconds() / clock.budget_s)
    return min(done, 1.0)
