"""Stage 2: joint neural radiative transfer (``nrt-train stage=rte``; ``stage=forward``).

Trains the light field ``L_theta`` and the medium ``M_phi`` (modulating the stage-1 EA
density) on ``L = w_rte L_RTE + w_bc L_BC + w_obs L_obs + w_vre L_VRE``, the objectives
``losses.objectives`` chooses (units of :mod:`nrt.losses.objective`, weights from
``losses.weights``; conf/losses/rte_paper.yaml). Only objectives with a positive weight
are evaluated, and only the terms the scene's effects declare (no g without HG, grey
coefficients without chromatic extinction, explicit first scattering only of the emitters
and sun the scene has). Each
objective is backpropagated on its own, so the time per step splits by objective
(``time/step_<name>_s``); gradients accumulate and one Adam step follows.

Forward mode (``stage=forward``): the medium is the dataset's ground truth and only the
light field learns (RTE + BC), which validates the solver against Mitsuba's renders.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from pathlib import Path

import torch

from nrt.data.grids import MEDIUM_GRIDS_FILE, save_property_grids
from nrt.errors import ConfigError, DatasetError, NrtError
from nrt.losses.objective import Objective, Scenes, build_objectives
from nrt.losses.samplers import DensityPointSampler, EnvironmentDirectionSampler
from nrt.metrics import psnr
from nrt.modules.fields.medium import GroundTruthMedium, Medium
from nrt.modules.fields.protocols import ModulatedMedium, RadianceField, build
from nrt.modules.renderers.exit import exit_radiance
from nrt.modules.renderers.volume import DirectSource, transmitted_background, vre_render
from nrt.modules.stages.components import (
    as_factory,
    factory_config,
    legacy_config,
    objective_components,
)
from nrt.modules.stages.ea import load_ea_field
from nrt.modules.stages.stage import Stage, check_learning_rates
from nrt.physics.direct_light import DirectLights, direct_inscatter, split_sun
from nrt.physics.envmap import EnvironmentMap, texel_directions
from nrt.physics.tonemap import luminance
from nrt.tensorboard import log_image

log = logging.getLogger(__name__)

PAPER_OBJECTIVES = {"rte": "nrt.losses.rte.RTEObjective",
                    "bc": "nrt.losses.boundary.BoundaryObjective",
                    "obs": "nrt.losses.observation.ObservationObjective",
                    "vre": "nrt.losses.vre.VREObjective"}
"""The paper formulation's objectives by name (conf/losses/rte_paper.yaml): those of a
checkpoint written before ``losses.objectives`` chose them."""
DENSITY_SOURCES = ("ea", "none", "ground_truth", "oracle")
"""Where stage 2's density comes from (``init.source``): an EA run, none, the ground truth
(forward mode), or the ground truth's extinction in place of the EA density (``oracle``:
a diagnostic of the split stage, docs/stage2.md)."""


def mean_radiance(envmap: EnvironmentMap) -> float:
    """Mean luminance of an environment over the sphere (rows weighted by solid angle)."""
    d = texel_directions(envmap.height, envmap.width)
    solid = torch.sqrt((1 - d[..., 1] ** 2).clamp_min(0.0))
    lum = luminance(envmap.radiance.double())
    return float((lum * solid).sum() / solid.sum().clamp_min(1e-30))


@dataclass
class Illumination:
    """One training environment E as stage 2 lights the medium with it: ``index`` (its
    position in the dataset's environments), E's sun-less part ``rest`` (the inflow of the
    light field; the sky's first scattering), the sun's part ``sun`` (``E - rest``; None
    without a sun), the known ``lights`` (E's suns and the
    scene's emitters), a ``sampler`` of directions like ``rest``, and ``scale``, E's mean
    luminance (the light field's ``radiance_scale``)."""

    index: int
    rest: EnvironmentMap
    sun: EnvironmentMap | None
    lights: DirectLights
    sampler: EnvironmentDirectionSampler
    scale: float


def make_illumination(index: int, env: EnvironmentMap, sun: dict | None, emitters: list[dict],
                      device: torch.device | str = "cpu") -> Illumination:
    """:class:`Illumination` of ``env`` (the dataset's environment ``index``) with the point
    ``emitters`` (``{position, intensity}``) and, when ``sun.threshold`` is set, E's texels
    brighter than ``threshold x scale`` split off as at most ``sun.max_suns`` suns."""
    scale = max(mean_radiance(env), 1e-6)
    sun = sun or {}
    if sun.get("threshold") is not None:
        rest, sun_dirs, sun_irr = split_sun(env, float(sun["threshold"]) * scale,
                                            int(sun.get("max_suns", 4)))
    else:
        rest, sun_dirs, sun_irr = env, torch.zeros(0, 3), torch.zeros(0, 3)
    lights = DirectLights(
        torch.tensor([e["position"] for e in emitters], dtype=torch.float32).reshape(-1, 3),
        torch.tensor([e["intensity"] for e in emitters], dtype=torch.float32).reshape(-1, 3),
        sun_dirs, sun_irr).to(device)
    if sun_dirs.shape[0]:
        log.info("Sun(s) of environment %d scattered explicitly: directions %s, irradiance %s",
                 index, sun_dirs.tolist(), sun_irr.tolist())
    part_of_sun = EnvironmentMap(env.radiance - rest.radiance).to(device) \
        if sun_dirs.shape[0] else None
    return Illumination(index, rest.to(device), part_of_sun, lights,
                        EnvironmentDirectionSampler(rest), scale)


class RadiativeTransferStage(Stage):
    """What every stage-2 formulation shares: the scene's effects (all scattering orders),
    the training environments (:class:`Illumination`: each with its suns and the emitters
    as known lights), the medium (the dataset's ground truth in forward mode), the
    validation baselines, the property grids that the metric callbacks score and the
    ``medium_grids.npz`` export. A subclass builds
    ``self.light`` (with ``bbox`` and ``radiance_scale`` buffers) and, when
    :attr:`learns_medium`, ``self.medium``, from the factories its config groups give
    (``model/light_field``, ``model/medium``; :mod:`nrt.modules.stages.components`), and implements
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

    def backward_objectives(self, batch: dict, scenes: Scenes) -> torch.Tensor:
        """Backpropagate each active objective (:meth:`active_weights`) on ``batch`` over
        ``scenes`` times its weight, logging its value and seconds; returns the weighted
        total (detached)."""
        total = torch.zeros((), device=self.device)
        for name, weight in self.active_weights().items():
            start = time.perf_counter()
            loss = self.objectives[name].loss(self, batch, scenes)
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

    def sunless(self, dirs: torch.Tensor) -> torch.Tensor:
        """Mask of view directions that do not look into the sun's texels (all without one)."""
        if self.sky.sun is None:
            return torch.ones(dirs.shape[0], dtype=torch.bool, device=dirs.device)
        return self.sky.sun.lookup(dirs).sum(-1) <= 0

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
        """Write ``medium_grids.npz`` (:mod:`nrt.data.grids`) at ``property_resolution``
        (default: the ground truth's, else 64)."""
        if not self.learns_medium:
            return {}
        res = self.grid_resolution(self.hparams.property_resolution, 64)
        path = save_property_grids(Path(run_dir) / MEDIUM_GRIDS_FILE, self.property_grids(res),
                                   self.medium.bbox)
        return {"medium_grids": str(path)}


FITS = ("The paper's formulation (experiment=rte_paper) takes model/light_field=siren and "
        "model/medium=siren or grid; the SH-grid light field and the voxel medium belong to "
        "the split stage (stage=rte without experiment=rte_paper)")


def legacy_medium(keywords: dict) -> dict:
    """A checkpoint's medium from before it was a component: ``modulation: siren|grid`` with
    ``siren: {...}`` or ``grid_resolution``, ``init_albedo`` (and ``parametrization``)."""
    rest = {k: v for k, v in keywords.items()
            if k not in ("modulation", "siren", "grid_resolution")}
    if keywords.get("modulation", "siren") == "grid":
        modulation = {"_target_": "nrt.modules.fields.medium.GridModulation",
                      "resolution": keywords.get("grid_resolution", 32)}
    else:
        modulation = {"_target_": "nrt.modules.encodings.siren.Siren", **keywords.get("siren", {})}
    return {"_target_": "nrt.modules.fields.medium.NeuralMedium", "_partial_": True,
            "modulation": {**modulation, "_partial_": True}, **rest}


class RTEModule(RadiativeTransferStage):
    """Light field + medium trained on the RTE, boundary, observation and VRE objectives."""

    def __init__(self, effects: dict, light_field: Callable[..., RadianceField] | dict,
                 medium: Callable[..., ModulatedMedium] | dict, density: dict,
                 weights: dict, samples: dict, lr: dict, detach_inscatter: bool = False,
                 lr_final_factor: float = 0.1, medium_warmup: float = 0.0,
                 sun: dict | None = None, grad_clip: float | None = None,
                 eval_chunk: int = 4096,
                 property_resolution: int | None = None,
                 objectives: Mapping[str, Callable[..., Objective] | dict] | None = None):
        super().__init__(effects, density, sun, property_resolution)
        if density["source"] == "oracle":
            raise ConfigError("init=oracle (the true extinction in place of the EA density) is "
                              "a diagnostic of the split stage 2 (stage=rte), not of "
                              "experiment=rte_paper; use init=ea or init=none.")
        make_objectives, objectives = objective_components(objectives, PAPER_OBJECTIVES)
        make_light = as_factory(light_field, "light_field",
                                legacy_config("nrt.modules.fields.light_field.LightField"))
        make_medium = as_factory(medium, "medium", legacy_medium)
        # the hyperparameters record the components' configs: a checkpoint pickles no code
        light_field, medium = factory_config(make_light), factory_config(make_medium)
        self.save_hyperparameters()
        self.automatic_optimization = False
        self.objectives = build_objectives(weights, make_objectives)
        check_learning_rates(lr, "model.lr", ("light", "medium")
                             + (("density",) if density.get("train") else ()))
        self.light: RadianceField = build(make_light, RadianceField, "light_field", FITS)
        if self.learns_medium:
            self.medium = build(make_medium, ModulatedMedium, "medium", FITS, effects,
                                self._ea_density(density))
        self._density_sampler: DensityPointSampler | None = None

    @staticmethod
    def _ea_density(density: dict) -> torch.nn.Module | None:
        """The EA field the medium modulates (``init=ea``), frozen or fine-tuned; None for
        ``init=none``."""
        if density["source"] != "ea":
            return None
        ckpt = density.get("ea_ckpt")
        ea = load_ea_field(ckpt)
        ea.requires_grad_(bool(density.get("train", False)))
        log.info("Stage 2 modulates the EA density of %s (%s)", ckpt,
                 "fine-tuned" if density.get("train") else "frozen")
        return ea

    def configure_optimizers(self):
        lr = self.hparams.lr
        groups = [{"params": list(self.light.parameters()), "lr": lr["light"]}]
        if self.learns_medium:
            density = self.medium.density_field
            dens_ids = {id(p) for p in density.parameters()} if density is not None else set()
            modulation = [p for p in self.medium.parameters() if id(p) not in dens_ids]
            groups.append({"params": modulation, "lr": lr["medium"]})
            if density is not None and self.hparams.density.get("train", False):
                groups.append({"params": list(density.parameters()), "lr": lr["density"]})
        opt = torch.optim.Adam(groups)
        factor, warmup = self.hparams.lr_final_factor, self.hparams.medium_warmup

        def decay(s: int) -> float:  # over the steps, or over budget_s in equal-time runs
            return factor ** self.progress()

        def medium(s: int) -> float:  # the medium waits until the light field is plausible
            return decay(s) if self.progress() >= warmup else 0.0
        sched = torch.optim.lr_scheduler.LambdaLR(opt, [decay] + [medium] * (len(groups) - 1))
        return [opt], [{"scheduler": sched, "interval": "step"}]

    def density_sampler(self) -> DensityPointSampler:
        """Collocation sampler following the current extinction (rebuilt each validation)."""
        if self._density_sampler is None:
            grids = self.medium.grids(int(self.hparams.samples.get("density_grid", 32)))
            sigma_t = luminance(grids["sigma_a"] + grids["sigma_s"])
            self._density_sampler = DensityPointSampler(sigma_t, self.medium.bbox)
        return self._density_sampler

    # --------------------------------------------------------------- training
    def training_step(self, batch: dict, batch_idx: int) -> torch.Tensor:
        opt = self.optimizers()
        opt.zero_grad(set_to_none=True)
        total = self.backward_objectives(batch, [(self.medium, self.light)])
        if self.hparams.grad_clip:
            self.clip_gradients(opt, gradient_clip_val=self.hparams.grad_clip)
        opt.step()
        self.lr_schedulers().step()
        return torch.as_tensor(total)

    # ------------------------------------------------------------- validation
    def predict_pixels(self, origins: torch.Tensor, dirs: torch.Tensor,
                       background: torch.Tensor) -> dict[str, torch.Tensor]:
        """Two predictions of ``L(o, -v)`` (R, 3) for view rays, chunked, without graph:
        ``vre`` (the VRE through the box with the light field's in-scattering: the image
        the method renders) and ``exit`` (the light field where the ray leaves the box,
        plus the sun seen through the medium)."""
        s, chunk, source = self.hparams.samples, self.hparams.eval_chunk, self.direct_source()
        out: dict[str, list] = {"vre": [], "exit": []}
        for i in range(0, len(origins), chunk):
            o, d, bg = origins[i:i + chunk], dirs[i:i + chunk], background[i:i + chunk]
            out["vre"].append(vre_render(self.light, self.medium, o, d, bg,
                                         int(s["vre_samples"]), int(s["vre_directions"]),
                                         jitter=False, direct_source=source)[0].detach())
            with torch.no_grad():
                sun_part = self.sky.sun
                sun = sun_part.lookup(d) if sun_part is not None else torch.zeros_like(bg)
                exit_ = exit_radiance(self.light, o, d, bg - sun)
                if sun_part is not None:
                    exit_ = exit_ + transmitted_background(self.medium, o, d, sun,
                                                           int(s["vre_samples"]))
            out["exit"].append(exit_)
        return {k: torch.cat(v) for k, v in out.items()}

    def on_validation_epoch_end(self) -> None:
        self._density_sampler = None  # follow the medium as it learns
