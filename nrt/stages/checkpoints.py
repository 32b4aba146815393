"""The checkpoint format of nrt's stages: every checkpoint a stage saves records
:data:`CHECKPOINT_FORMAT` under :data:`FORMAT_KEY`, and every checkpoint nrt reads (a resume,
an EA start, ``nrt-eval``, ``nrt-sample``) is refused unless it has that format.

Format 2: Lightning's checkpoint dict; each component a stage receives (density field,
light field, medium, objectives, the split stage 2's scene source) recorded in
``hyper_parameters`` as its Hydra config (``_target_``, ``_partial_: true``, keywords), so
that no code is pickled. Generative stage 2 is the split stage with a scene family
(:mod:`nrt.stages.family`): its config is ``hyper_parameters["scenes"]`` and its state
(the codes, the frozen EA field) is under ``scenes.``.

A checkpoint of any other format, or one that records none (written before formats were
recorded), is refused with its version and the fix: nrt converts no checkpoint. A resume
whose config groups the optimiser's parameters otherwise than the checkpoint's run did
(:func:`check_optimizer_layout`) is refused too, rather than left to load one run's moments
into another's parameters.
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


def stamp(checkpoint: dict) -> None:
    """Record :data:`CHECKPOINT_FORMAT` in ``checkpoint`` (a stage's ``on_save_checkpoint``)."""
    checkpoint[FORMAT_KEY] = CHECKPOINT_FORMAT


def reads(checkpoint: dict) -> bool:
    """Whether this nrt reads ``checkpoint``: it records :data:`CHECKPOINT_FORMAT`."""
    return checkpoint.get(FORMAT_KEY) == CHECKPOINT_FORMAT


def check_format(checkpoint: dict, source: str | Path) -> None:
    """Refuse ``checkpoint`` (read from ``source``) unless this nrt reads it (:func:`reads`)."""
    if reads(checkpoint):
        return
    version = checkpoint.get(FORMAT_KEY)
    if version is None:
        found = "records no checkpoint format: an nrt older than format 2 wrote it"
    else:
        age = "an older" if isinstance(version, int) and version < CHECKPOINT_FORMAT \
            else "another"
        found = f"has checkpoint format {version!r}, written by {age} nrt"
    raise NrtError(f"checkpoint '{source}' {found}; this nrt reads format {CHECKPOINT_FORMAT} "
                   "only and converts none. Train the stage again with this nrt (nrt-train "
                   "stage=<stage> scene=<scene>), or read the checkpoint with the nrt version "
                   "that wrote it.")


def optimizer_layout(param_groups: list[dict]) -> list[tuple[int, bool]]:
    """An optimiser's groups as a resume must find them again: per group its number of
    parameters and whether it steps per member (``members``,
    :class:`~nrt.stages.member_adam.MemberAdam`). ``param_groups``: an optimiser's
    ``param_groups`` or those of its ``state_dict()``."""
    return [(len(group["params"]), "members" in group) for group in param_groups]


def check_optimizer_layout(saved: list[list[tuple[int, bool]]],
                           current: list[list[tuple[int, bool]]], source: str | Path) -> None:
    """Refuse a resume from ``source`` whose optimisers' layouts (:func:`optimizer_layout`,
    one list per optimiser) ``saved`` differ from the run's ``current`` ones."""
    if saved == current:
        return
    raise NrtError(f"checkpoint '{source}' groups its optimiser's parameters as {saved} "
                   f"(per group: parameters, steps per member), but this config groups them "
                   f"as {current}: the resume changed a setting that decides which "
                   "parameters the run learns or how Adam steps them (e.g. "
                   "mode.latent.per_member_adam, mode.latent.member_offsets, "
                   "mode.latent.light_offsets, the learned properties). Resume with the "
                   "settings of the run that wrote the checkpoint (its .hydra/config.yaml), "
                   "or start a new run without resume.")


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
