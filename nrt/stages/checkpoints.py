"""The checkpoint format of nrt's stages: every checkpoint a stage saves records
:data:`CHECKPOINT_FORMAT` under :data:`FORMAT_KEY`, and every checkpoint nrt reads (a resume,
an EA start, ``nrt-eval``, ``nrt-sample``) is refused unless it has that format.

Format 2: Lightning's checkpoint dict; each component a stage receives (density field,
light field, medium, objectives, the split stage 2's scene source) recorded in
``hyper_parameters`` as its Hydra config (``_target_``, ``_partial_: true``, keywords), so
that no code is pickled. Generative stage 2 is the split stage with a scene family
(:mod:`nrt.stages.family`): its config is ``hyper_parameters["scenes"]`` and its state
(the codes, the frozen EA field) is under ``scenes.``.

Format 1 differs only there: generative stage 2 was a stage class of its own, with its
settings and state at the top (``hyper_parameters["ea_field"]``, ``codes``). Every other
checkpoint of format 1 reads as format 2, including those written before the format was
recorded (no key); a generative stage 2 of format 1, and any other recorded number (one
of a newer nrt), is refused.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import torch

from nrt.errors import NrtError

CHECKPOINT_FORMAT = 2
"""The format this nrt writes and reads."""
FORMAT_KEY = "nrt_checkpoint_format"
"""The checkpoint dict's key that records the format."""
UNRECORDED_FORMAT = 1
"""The format of a checkpoint that records none."""


def stamp(checkpoint: dict) -> None:
    """Record :data:`CHECKPOINT_FORMAT` in ``checkpoint`` (a stage's ``on_save_checkpoint``)."""
    checkpoint[FORMAT_KEY] = CHECKPOINT_FORMAT


def reads(checkpoint: dict) -> bool:
    """Whether this nrt reads ``checkpoint``: format 2, or format 1 of any stage but
    generative stage 2 (whose layout format 2 changed: ``ea_field`` among its
    hyperparameters)."""
    version = checkpoint.get(FORMAT_KEY, UNRECORDED_FORMAT)
    if version == 1:
        return "ea_field" not in (checkpoint.get("hyper_parameters") or {})
    return version == CHECKPOINT_FORMAT


def check_format(checkpoint: dict, source: str | Path) -> None:
    """Refuse ``checkpoint`` (read from ``source``) unless this nrt reads it (:func:`reads`)."""
    if not reads(checkpoint):
        version = checkpoint.get(FORMAT_KEY, UNRECORDED_FORMAT)
        age = "an older" if isinstance(version, int) and version < CHECKPOINT_FORMAT \
            else "another"
        raise NrtError(f"checkpoint '{source}' has checkpoint format {version!r}, written by "
                       f"{age} nrt; this nrt reads format {CHECKPOINT_FORMAT} (and format 1 "
                       "of every stage but generative stage 2) and converts none. Train the "
                       "stage again with this nrt (nrt-train stage=<stage> scene=<scene>), or "
                       "read the checkpoint with the nrt version that wrote it.")


def check_checkpoint_file(ckpt_path: str | Path | None, first_stage: str) -> None:
    """Refuse an ``init.ea_ckpt`` that is no file, naming ``first_stage``, the command that
    trains the stage-1 run."""
    if not ckpt_path or not Path(ckpt_path).is_file():
        raise NrtError(f"init.ea_ckpt='{ckpt_path}' is not a checkpoint file. Train stage 1 "
                       f"first ({first_stage}) and pass its checkpoints/last.ckpt, or drop "
                       "init.ea_ckpt to start from the newest EA run of the scene "
                       "(single-scene stage 2 also runs without a first stage: init=none).")


def read_checkpoint(ckpt_path: str | Path) -> dict[str, Any]:
    """The checkpoint dict at ``ckpt_path`` on the CPU (memory-mapped), its format checked."""
    saved = torch.load(ckpt_path, map_location="cpu", weights_only=False, mmap=True)
    check_format(saved, ckpt_path)
    return saved


def load_stage(cls: type, ckpt_path: str | Path, map_location: str | torch.device = "cpu"):
    """``cls.load_from_checkpoint(ckpt_path)`` (a Lightning module class), its format checked
    first."""
    read_checkpoint(ckpt_path)
    return cls.load_from_checkpoint(ckpt_path, map_location=map_location)
