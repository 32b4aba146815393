"""Where stage 2 (and the baseline) start: the density source (``init``), the EA checkpoint
it comes from, and the density baked into the medium (:class:`DensityStart`).

``nrt-train`` resolves the EA checkpoint with :func:`resolve_ea_checkpoint` before it
builds the stage; the stage bakes the start into its medium once the datamodule (the box,
the ground truth) is known. Densities are extinctions per unit length; the oracle blend is
geometric, in the log space the medium modulates (docs/stage2.md, "The start decides the
end").
"""

from __future__ import annotations

import logging
from collections.abc import Mapping
from pathlib import Path

import torch

from nrt.errors import ConfigError, DatasetError, NrtError
from nrt.physics.volume import sample_grid
from nrt.run_dirs import LAST_CKPT, latest_run_with_checkpoint, run_dataset
from nrt.stages.checkpoints import check_checkpoint_file
from nrt.stages.ea import load_ea_field

log = logging.getLogger(__name__)

DENSITY_SOURCES = ("ea", "none", "ground_truth", "oracle")
"""Where stage 2's density comes from (``init.source``): an EA run, none, the ground truth
(forward mode), or the ground truth's extinction in place of the EA density (``oracle``:
a diagnostic of the split stage, docs/stage2.md)."""

BLEND_FLOOR = 1e-4
"""Extinction (per unit length) below which a density counts as this floor in
:func:`geometric_blend`, so that an empty cell of either side does not zero the blend."""


def truth_share(density: Mapping) -> float:
    """``init.truth_share`` of an ``init=oracle`` start, in [0, 1] (1, the truth alone, when
    unset); a clear error otherwise."""
    share = density.get("truth_share", 1.0)
    share = 1.0 if share is None else float(share)
    if not 0.0 <= share <= 1.0:
        raise ConfigError(f"init.truth_share={share}: the truth's share of the start (init=oracle) "
                          "must lie in [0, 1]; 1 starts from the truth, 0.5 halfway from the EA "
                          "density to it.")
    return share


def geometric_blend(ea: torch.Tensor, truth: torch.Tensor, share: float) -> torch.Tensor:
    """``ea^(1 - share) truth^share``, each floored at :data:`BLEND_FLOOR`: the start halfway
    (``share`` 0.5) between two extinctions in the log space the medium modulates."""
    return ea.clamp_min(BLEND_FLOOR) ** (1.0 - share) * truth.clamp_min(BLEND_FLOOR) ** share


def needs_ea_checkpoint(density: Mapping) -> bool:
    """Whether a start (``init``: ``source``, ``truth_share``) reads an EA run: ``init=ea``,
    and ``init=oracle`` blended with one (``truth_share`` < 1)."""
    if density.get("source") == "oracle":
        return truth_share(density) < 1.0
    return density.get("source") == "ea"


def resolve_ea_checkpoint(density: Mapping, scene: str, stage: str, output_dir: str | Path,
                          recorded: str | None = None,
                          dataset: str | None = None) -> str | None:
    """The EA checkpoint whose density a stage starts from, as an absolute path; None for a
    start that reads none (:func:`needs_ea_checkpoint`).

    ``density["ea_ckpt"]`` (``init.ea_ckpt``) when given; else ``recorded`` (the one a resumed
    run started from); else the newest EA run of ``scene`` under ``output_dir`` that saved a
    checkpoint, among those trained on ``dataset`` (the name of the stage's own dataset
    folder, when known): an EA run of another preset or photo realisation is never picked
    silently. Errors name the command that trains one."""
    if not needs_ea_checkpoint(density):
        return None
    if density.get("ea_ckpt"):
        path = Path(str(density["ea_ckpt"])).expanduser()
        check_checkpoint_file(str(path), f"nrt-train stage=ea scene={scene}")
    elif recorded and Path(recorded).is_file():
        path = Path(recorded)
    else:
        base = Path(output_dir) / scene / "ea"
        run = latest_run_with_checkpoint(base, dataset)
        if run is None:
            other = latest_run_with_checkpoint(base)
            found = (f"the EA runs under '{base}' trained on other photos (the newest, "
                     f"'{other}', on '{run_dataset(other)}'; this run's are '{dataset}': "
                     "another preset or photo realisation)" if other is not None
                     else f"no EA run under '{base}' saved {LAST_CKPT}")
            raise NrtError(f"stage={stage} starts from the EA density of scene '{scene}', but "
                           f"{found}. Run `nrt-train stage=ea scene={scene}` with this run's "
                           "preset and scene overrides first, pass init.ea_ckpt=<path/to/"
                           "last.ckpt> to start from a run of your choice, or use init=none "
                           "for the single-stage ablation.")
        path = run / LAST_CKPT
    return str(path.resolve())


class DensityStart:
    """The density a voxel medium modulates, from ``init`` (``density``: ``source``,
    ``ea_ckpt``, ``truth_share``): the EA run's density (``init=ea``), or with ``init=oracle``
    the dataset's true extinction (its channel mean), or with ``init.truth_share`` a < 1 the
    geometric blend ``EA^(1 - a) truth^a``. :meth:`bake` sets it into the medium."""

    def __init__(self, density: Mapping):
        self.source = density["source"]
        self.ea_ckpt = density.get("ea_ckpt")
        self.share = truth_share(density) if self.source == "oracle" else 0.0
        if self.source == "oracle" and self.share < 1.0 and not self.ea_ckpt:
            raise ConfigError("init=oracle with init.truth_share < 1 blends the truth with an EA "
                              "run's density: pass init.ea_ckpt=<path/to/last.ckpt>.")

    @property
    def bakes(self) -> bool:
        """Whether this start sets a density into the medium (``init=ea`` or ``oracle``)."""
        return self.source in ("ea", "oracle")

    def bake(self, medium, ground_truth: Mapping[str, torch.Tensor] | None) -> None:
        """Set the start's density into ``medium`` (its ``set_density`` and ``bbox``);
        ``ground_truth`` (the dataset's grids) for ``init=oracle``."""
        if self.source != "oracle":
            ea = load_ea_field(self.ea_ckpt).to(medium.bbox.device)
            medium.set_density(ea.density)
            log.info("Stage 2 modulates the EA density of %s", self.ea_ckpt)
            return
        if ground_truth is None:
            raise DatasetError("init=oracle needs the dataset's ground_truth.npz (the true "
                               "extinction it starts from); this dataset has none.")
        true_extinction = (ground_truth["sigma_a"] + ground_truth["sigma_s"]).float().mean(
            -1, keepdim=True)
        bbox = medium.bbox

        def true_density(x: torch.Tensor) -> torch.Tensor:
            return sample_grid(true_extinction.to(x.device), x, bbox)[..., 0]

        if self.share == 1.0:
            medium.set_density(true_density)
            log.info("Stage 2 modulates the TRUE extinction (init=oracle, a diagnostic)")
            return
        ea = load_ea_field(self.ea_ckpt).to(bbox.device)
        share = self.share
        medium.set_density(lambda x: geometric_blend(ea.density(x), true_density(x), share))
        log.info("Stage 2 modulates EA^%.2f x TRUTH^%.2f (init=oracle, a diagnostic), the EA "
                 "density of %s", 1.0 - share, share, self.ea_ckpt)
