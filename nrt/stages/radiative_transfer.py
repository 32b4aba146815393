"""What every stage-2 formulation shares (:class:`RadiativeTransferStage`): the scene's
effects (all scattering orders), the training environments (:mod:`nrt.stages.illumination`),
the medium (the dataset's ground truth in forward mode), the objectives' weighted
backward pass, validation, the property grids and the ``medium_grids.npz`` export.

Radiance is linear RGB; a view ray's pixel is ``L(o, -v)`` (docs/conventions.md).
"""

from __future__ import annotations

import time
from pathlib import Path

import torch
from torch.profiler import record_function

from nrt.data.grids import MEDIUM_GRIDS_FILE, save_property_grids
from nrt.errors import DatasetError, NrtError
from nrt.losses.context import Illumination, StepContext
from nrt.losses.objective import Objective
from nrt.metrics import psnr
from nrt.modules.fields.medium import GroundTruthMedium, Medium
from nrt.modules.renderers.volume import DirectSource, transmitted_background
from nrt.physics.direct_light import direct_inscatter
from nrt.stages.illumination import make_illumination
from nrt.stages.stage import Stage
from nrt.stages.start import DENSITY_SOURCES
from nrt.tensorboard import log_image


class RadiativeTransferStage(Stage):
    """What every stage-2 formulation shares: the scene's effects (all scattering orders),
    the training environments (:class:`Illumination`: each with its suns and the emitters
    as known lights), the medium (the dataset's ground truth in forward mode), the
    validation baselines, the property grids that the metric callbacks score and the
    ``medium_grids.npz`` export. A subclass builds
    ``self.light`` (with ``bbox`` and ``radiance_scale`` buffers) and, when
    :attr:`learns_medium`, ``self.medium``, from the factories its config groups give
    (``model/light_field``, ``model/medium``; :mod:`nrt.stages.components`), and implements
    training and :meth:`predict_pixels`."""

    MANY_ENVIRONMENTS = False
    """Whether the stage trains on the photos of several environments at once (one light
    field each); a stage that does not refuses ``stage.environments`` naming more than one."""

    def __init__(self, effects: dict, density: dict, sun: dict | None,
                 property_resolution: int | None):
        super().__init__(effects)
        if int(effects.get("max_scattering_order", -1)) != -1:
            raise NrtError(
                f"scene.effects.max_scattering_order={effects['max_scattering_order']}: the RTE "
                "stage solves for the full radiance (all scattering orders) and cannot match "
                "photos rendered with truncated transport. Render the scene with -1 to train "
                "stage 2 on it.")
        if density["source"] not in DENSITY_SOURCES:
            raise NrtError(f"init.source must be one of {list(DENSITY_SOURCES)} for stage 2, "
                           f"got '{density['source']}' (init=grids starts stage=dpt only).")
        self.learns_medium = density["source"] != "ground_truth"
        """False in forward mode, whose medium is the dataset's ground truth (set up later)."""
        self.medium: Medium | None = None
        self.illuminations: list[Illumination] = []  # the training environments, set up
        self.objectives: dict[str, Objective] = {}  # by name, in the order of losses.weights

    def active_weights(self) -> dict[str, float]:
        """The objectives whose weight is positive at this step, with their weights."""
        step, progress = self.global_step, self.progress()
        return {name: w for name, unit in self.objectives.items()
                if (w := unit.weight(step, progress)) > 0}

    def step_context(self, scenes) -> StepContext:
        """What the objectives read this step besides the batch, over ``scenes`` (the
        step's (medium, light) pairs): the first environment's illumination and the known
        lights' first scattering; a formulation adds its own sources."""
        return StepContext(scenes, self.sky, direct_source=self.direct_source())

    def backward_objectives(self, batch: dict, context: StepContext) -> torch.Tensor:
        """Backpropagate each active objective (:meth:`active_weights`) on ``batch`` in the
        step's ``context`` times its weight, logging its value and seconds; returns the
        weighted total (detached). The loss and its backward run in the profiler scopes
        ``nrt/objective/<name>/forward`` and ``.../backward`` (benchmarks.profile_step)."""
        total = torch.zeros((), device=self.device)
        for name, weight in self.active_weights().items():
            start = time.perf_counter()
            with record_function(f"nrt/objective/{name}/forward"):
                loss = self.objectives[name].loss(batch, context)
            with record_function(f"nrt/objective/{name}/backward"):
                self.manual_backward(weight * loss)
                if self.device.type == "cuda":
                    torch.cuda.synchronize(self.device)
            self.log(f"time/step_{name}_s", time.perf_counter() - start)
            self.log(f"train/loss_{name}", loss.detach())
            total = total + weight * loss.detach()
        self.log("train/loss", total, prog_bar=True)
        return total

    # ----------------------------------------------------------------- set-up
    def setup(self, stage: str) -> None:
        dm = self.datamodule()
        if dm is None:
            return
        bbox = dm.bbox.to(self.device)
        if self.medium is None:
            gt = dm.ground_truth
            if gt is None:
                raise NrtError(f"Dataset '{dm.dataset_dir}' has no ground_truth.npz; forward "
                               "mode (init.source=ground_truth) needs the true medium.")
            self.medium = GroundTruthMedium(self.effects, gt["sigma_a"], gt["sigma_s"], gt["g"],
                                            bbox).to(self.device)
        self.medium.bbox.copy_(bbox)
        self.light.bbox.copy_(bbox)
        maps = dm.training_environments()
        if len(maps) > 1 and not self.MANY_ENVIRONMENTS:
            raise DatasetError(
                f"Dataset '{dm.dataset_dir}': this stage learns the light field of one "
                f"environment, but stage.environments selects {len(maps)}; choose one with "
                "stage.environments=[<name or position>] (the split stage, stage=rte, trains "
                "on several).")
        self.illuminations = [make_illumination(index, env, self.hparams.sun,
                                                self.effects.get("emitters") or [], self.device)
                              for index, env in maps.items()]
        self.light.radiance_scale.fill_(self.illuminations[0].scale)

    @property
    def sky(self) -> Illumination | None:
        """The first training environment: the only one of a stage that learns one light
        field (:attr:`MANY_ENVIRONMENTS` false); None before set-up."""
        return self.illuminations[0] if self.illuminations else None

    def direct_source(self) -> DirectSource | None:
        """First scattering of the known lights (emitters, suns), or None without any."""
        if self.sky is None or len(self.sky.lights) == 0:
            return None
        n_steps = int(self.hparams.samples.get("shadow_steps", 16))

        def source(x, w, props):
            return direct_inscatter(x, w, props.g, self.sky.lights,
                                    lambda p: self.medium(p).sigma_t, self.medium.bbox, n_steps)
        return source

    # ------------------------------------------------------------- validation
    def predict_view(self, batch: dict) -> dict[str, torch.Tensor]:
        """:meth:`predict_pixels` of a validation batch (a family member's view in the
        generative stage)."""
        return self.predict_pixels(batch["origins"], batch["dirs"], batch["background"])

    def validation_step(self, batch: dict, batch_idx: int) -> dict[str, torch.Tensor]:
        """Scores one held-out view; the output carries ``member`` when the batch does."""
        h, w = batch["shape"]
        ref = batch["rgb"]
        pred = self.predict_view(batch)
        self.log("val/psnr_exit", psnr(pred["exit"], ref), batch_size=1)
        scale = self.light.radiance_scale
        self.log("val/image_mse", torch.mean(((pred["vre"] - ref) / scale) ** 2), batch_size=1)
        for key, value in self.view_baselines(batch).items():
            self.log(f"val/{key}", value, batch_size=1)
        if batch_idx == 0:
            log_image(self, "val/vre|exit|truth", torch.cat(
                [p.reshape(h, w, 3) for p in (pred["vre"], pred["exit"], ref)], 1))
        out = {"image": pred["vre"].reshape(h, w, 3), "reference": ref.reshape(h, w, 3)}
        if batch.get("member") is not None:
            out["member"] = int(batch["member"])
        return out

    def more_baselines(self, batch: dict) -> dict[str, float]:
        """The no-scattering prediction's PSNR: the true medium's transmitted background
        ``T E(v)``, when ground truth exists."""
        gt = self.ground_truth()
        if gt is None:
            return {}
        true = GroundTruthMedium(self.effects, gt["sigma_a"], gt["sigma_s"], gt["g"],
                                 self.medium.bbox.cpu()).to(self.device)
        with torch.no_grad():
            t_e = transmitted_background(true, batch["origins"], batch["dirs"],
                                         batch["background"],
                                         int(self.hparams.samples["vre_samples"]))
        return {"psnr_transmitted_only": float(psnr(t_e, batch["rgb"]))}

    def property_grids(self, resolution: int) -> dict[str, torch.Tensor] | None:
        """The learned medium on R^3 cells (ground-truth layout); None in forward mode."""
        if not self.learns_medium:
            return None
        return self.medium.grids(resolution)

    def medium_bbox(self) -> torch.Tensor | None:
        return self.medium.bbox if self.medium is not None else None

    # ------------------------------------------------------------------ export
    def export(self, run_dir: str | Path) -> dict[str, str]:
        """Write ``medium_grids.npz`` (:mod:`nrt.data.grids`) of :meth:`property_grids` at
        ``property_resolution`` (default: the ground truth's, else 64); nothing without
        them (forward mode, a family's media)."""
        if not self.learns_medium:
            return {}
        res = self.grid_resolution(self.hparams.property_resolution, 64)
        grids = self.property_grids(res)
        if grids is None:
            return {}
        path = save_property_grids(Path(run_dir) / MEDIUM_GRIDS_FILE, grids, self.medium.bbox)
        return {"medium_grids": str(path)}
