"""The paper's stage 2 (``nrt-train stage=rte experiment=rte_paper``; ``stage=forward
experiment=rte_paper``): joint neural radiative transfer.

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
from collections.abc import Callable, Mapping

import torch

from nrt.errors import ConfigError
from nrt.losses.context import StepContext
from nrt.losses.objective import Objective, build_objectives
from nrt.losses.samplers import DensityPointSampler
from nrt.modules.fields.coarse_to_fine import decaying_lr, ramp_in
from nrt.modules.fields.protocols import ModulatedMedium, RadianceField, build
from nrt.modules.renderers.exit import exit_radiance
from nrt.modules.renderers.volume import transmitted_background, vre_render
from nrt.physics.tonemap import luminance
from nrt.stages.components import stage_2_components
from nrt.stages.ea import load_ea_field
from nrt.stages.radiative_transfer import RadiativeTransferStage
from nrt.stages.stage import check_learning_rates

log = logging.getLogger(__name__)

FITS = ("The paper's formulation (experiment=rte_paper) takes model/light_field=siren and "
        "model/medium=siren or grid; the SH-grid light field and the voxel medium belong to "
        "the split stage (stage=rte without experiment=rte_paper)")


class PaperRTEStage(RadiativeTransferStage):
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
        (make_light, make_medium, make_objectives), (light_field, medium, objectives) = \
            stage_2_components(light_field, medium, objectives)
        self.save_hyperparameters()  # the components' configs
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
            groups.append({"params": modulation, "lr": lr["medium"], "ramps_in": True})
            if density is not None and self.hparams.density.get("train", False):
                groups.append({"params": list(density.parameters()), "lr": lr["density"],
                               "ramps_in": True})
        opt = torch.optim.Adam(groups)
        warmup = self.hparams.medium_warmup
        # the medium waits (rate 0) until the light field is plausible, then takes the decay
        sched = decaying_lr(opt, self.hparams.lr_final_factor, self.progress,
                            lambda: ramp_in(self.progress(), warmup, 0.0))
        return [opt], [{"scheduler": sched, "interval": "step"}]

    def step_context(self, scenes) -> StepContext:
        """The base's context with collocation points drawn like the current extinction."""
        context = super().step_context(scenes)
        context.density_sampler = self.density_sampler
        return context

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
        total = self.backward_objectives(batch, self.step_context([(self.medium, self.light)]))
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
