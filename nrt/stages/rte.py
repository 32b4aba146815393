"""Stage 2 with the first collision split off (``nrt-train stage=rte``, the default).

The RTE is linear, so the radiance splits into the uncollided light and the light
scattered at least once, and only the second is learned:

- uncollided: ``T E(v)`` for the camera rays; inside the medium the sun-less sky's first
  scattering by MIS shadow rays (:func:`~nrt.physics.sky_light.sky_inscatter`) and the
  suns' and emitters' by shadow rays (:mod:`~nrt.physics.direct_light`): exact up to
  Monte Carlo noise, and differentiated with respect to the medium;
- scattered: a light field chosen by ``model/light_field`` (the protocol
  :class:`~nrt.modules.fields.protocols.ScatteredLightField`), by default
  :class:`~nrt.modules.fields.sh_light_field.SHGridLightField`, SH coefficients on a grid, zero on
  inflow and smooth in direction, whose in-scattering is exact for HG.

Two objectives, chosen by ``losses.objectives`` (their weights in ``losses.weights``):

- ``photo``: the training photos against the VRE of the camera rays with that
  in-scattering (:mod:`~nrt.losses.photo`); it trains the medium. The scattered light's
  coefficients enter it without gradient (their dependence on the medium is carried by
  the transport objective between steps), its ``g^l`` factors with gradient;
- ``transport``: the integral form of the RTE for the scattered light
  (:mod:`~nrt.losses.transport`); it trains the light field only.

The medium is chosen by ``model/medium`` (the protocol
:class:`~nrt.modules.fields.protocols.VoxelisedMedium`), by default
:class:`~nrt.modules.fields.voxel_medium.VoxelMedium`: the frozen EA density baked on a grid,
modulated by a grid that doubles during the run. The SH projection of the uncollided light
at the light field's cache points is refreshed from the current medium every
``samples.uncollided_every`` steps. The photo objective starts after ``light_warmup`` of
the run, so the medium does not explain light the light field has not learned yet.

Forward mode (``stage=forward``): the medium is the dataset's ground truth and only the
transport objective runs.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable, Mapping

import torch
from torch import nn

from nrt.errors import ConfigError
from nrt.losses.adjoint import adjoint_loss, medium_sensitivity
from nrt.losses.context import Illumination, StepContext
from nrt.losses.objective import Objective, build_objectives, objective_class
from nrt.losses.samplers import uniform_box_points
from nrt.losses.transport import uniform_samples, unrolled_inscatter
from nrt.modules.fields.coarse_to_fine import decaying_lr
from nrt.modules.fields.protocols import ScatteredLightField, VoxelisedMedium, build
from nrt.modules.fields.sh_light_field import SHGrid, SHGridLightField
from nrt.modules.fields.voxel_medium import detached, extinction
from nrt.modules.renderers.exit import exit_radiance
from nrt.modules.renderers.volume import render_view_rays, transmitted_background
from nrt.physics.direct_light import direct_inscatter
from nrt.physics.sky_light import sky_inscatter, uncollided_sh
from nrt.stages.components import stage_2_components
from nrt.stages.radiative_transfer import RadiativeTransferStage
from nrt.stages.stage import check_learning_rates
from nrt.stages.start import DensityStart

log = logging.getLogger(__name__)

FITS = ("The split stage (stage=rte, stage=forward) takes model/light_field=sh_grid and "
        "model/medium=voxel; the SIREN light field and the siren or grid media belong to the "
        "paper's formulation (experiment=rte_paper)")


COUPLING = {"unrolled_directions": 0, "unrolled_samples": 8, "adjoint": False,
            "adjoint_blend": 0.5}
"""``model.coupling``'s keys and defaults: the photos' gradient through the scattered light
(off by default; docs/stage2.md, "Coupling")."""


class RTEStage(RadiativeTransferStage):
    """A scattered-light field and a voxelised medium (by default the SH grid and the voxel
    medium) on the photo and transport objectives. The objectives and renderings take the
    medium and the light as arguments, so the generative stage
    (:mod:`nrt.stages.generative_rte`) runs them per family member."""

    LIGHT_PROTOCOL: type = ScatteredLightField
    MEDIUM_PROTOCOL: type = VoxelisedMedium
    FITS = FITS
    MANY_ENVIRONMENTS = True
    voxel_media = True

    def __init__(self, effects: dict, light_field: Callable[..., ScatteredLightField] | dict,
                 medium: Callable[..., VoxelisedMedium] | dict, density: dict,
                 weights: dict, samples: dict, lr: dict, lr_final_factor: float = 0.1,
                 light_warmup: float = 0.05,
                 sun: dict | None = None, eval_chunk: int = 4096,
                 property_resolution: int | None = None, coupling: dict | None = None,
                 objectives: Mapping[str, Callable[..., Objective] | dict] | None = None):
        super().__init__(effects, density, sun, property_resolution)
        (make_light, make_medium, make_objectives), (light_field, medium, objectives) = \
            stage_2_components(light_field, medium, objectives)
        self.save_hyperparameters()  # the components' configs
        self.automatic_optimization = False
        waits = {name: light_warmup for name, make in make_objectives.items()
                 if objective_class(make, f"losses.objectives.{name}").medium_only}
        self.objectives = build_objectives(
            weights, make_objectives, waits,
            " (the paper's four, rte/bc/obs/vre, are experiment=rte_paper)")
        if not self.learns_medium:  # forward mode: no medium to teach
            self.objectives = {name: unit for name, unit in self.objectives.items()
                               if not unit.medium_only}
        check_learning_rates(lr, "model.lr", ("light", "medium"))
        self.light = build(make_light, self.LIGHT_PROTOCOL, "light_field", self.FITS,
                           effects=effects)
        self._make_light = make_light
        self.more_lights = nn.ModuleList()  # the 2nd, 3rd ... training environment's
        self._scene_of_env = torch.zeros(0, dtype=torch.long)  # dataset env -> its light
        if self.learns_medium:  # init=none: the modulation alone (rho = 1)
            self.medium = build(make_medium, self.MEDIUM_PROTOCOL, "medium", self.FITS, effects)
        unknown = set(coupling or {}) - set(COUPLING)
        if unknown:
            raise ConfigError(f"model.coupling has unknown keys {sorted(unknown)}; the keys are "
                              f"{list(COUPLING)} (conf/model/rte.yaml).")
        self.coupling = {**COUPLING, **(coupling or {})}
        self.adjoint: SHGridLightField | None = None  # the adjoint grid, with coupling.adjoint
        if self.coupling["adjoint"] and self.learns_medium:
            if not isinstance(self.light, SHGridLightField):
                raise ConfigError("model.coupling.adjoint=true needs model/light_field=sh_grid "
                                  "(the adjoint is solved on the same SH grid).")
            self.adjoint = SHGridLightField(self.light.degree, self.light.resolution)
            self.register_buffer("adjoint_source", torch.zeros_like(self.light.coefficients))
        self._photo_coefficients: torch.Tensor | None = None
        self.start = DensityStart(density)
        self._baked = False
        self._uncollided_fresh = False

    # ----------------------------------------------------------------- set-up
    def setup(self, stage: str) -> None:
        super().setup(stage)
        if self.illuminations:
            self.add_lights(len(self.illuminations))
            if len(self.illuminations) > 1 and self.adjoint is not None:
                raise ConfigError("model.coupling.adjoint=true solves the adjoint of one "
                                  "environment's light; train on one (stage.environments=[0]).")
            for light, sky in zip(self.env_lights, self.illuminations, strict=True):
                light.bbox.copy_(self.light.bbox)
                light.radiance_scale.fill_(sky.scale)
            indices = [sky.index for sky in self.illuminations]
            self._scene_of_env = torch.full((max(indices) + 1,), -1, dtype=torch.long)
            self._scene_of_env[indices] = torch.arange(len(indices))
            if len(self.illuminations) > 1:
                log.info("Stage 2 trains on %d environments, a light field each",
                         len(self.illuminations))
        if self.learns_medium and self.start.bakes and not self._baked \
                and self.datamodule() is not None:
            self.bake_density()  # a resumed run loads the same values
            self._baked = True

    @property
    def env_lights(self) -> list[ScatteredLightField]:
        """The light field of each training environment, in the order of
        :attr:`illuminations`."""
        return [self.light, *self.more_lights]

    def add_lights(self, count: int) -> None:
        """Build light fields until there is one for each of ``count`` environments."""
        while len(self.env_lights) < count:
            self.more_lights.append(build(self._make_light, self.LIGHT_PROTOCOL, "light_field",
                                          self.FITS, effects=self.effects).to(self.device))

    def illumination_of(self, light: ScatteredLightField) -> Illumination:
        """The environment ``light`` is the scattered light of. A light that is not one of
        :attr:`env_lights` (a family member's, the adjoint's read of the stage's own) comes
        from a stage with one environment, the first."""
        for field, sky in zip(self.env_lights, self.illuminations, strict=True):
            if light is field:
                return sky
        return self.illuminations[0]

    def bake_density(self) -> None:
        """Bake the start (:class:`~nrt.stages.start.DensityStart`: the EA run's density, or
        with ``init=oracle`` the truth or its blend with it) into the medium."""
        self.start.bake(self.medium, self.datamodule().ground_truth)

    def param_groups(self) -> list[dict]:
        """Adam's groups: the light field's parameters and the medium's (``model.lr``)."""
        lr = self.hparams.lr
        groups = [{"params": [p for light in self.env_lights for p in light.parameters()],
                   "lr": lr["light"]}]
        if self.adjoint is not None:
            groups.append({"params": list(self.adjoint.parameters()), "lr": lr["light"]})
        if self.learns_medium:
            groups.append({"params": list(self.medium.parameters()), "lr": lr["medium"]})
        return groups

    def configure_optimizers(self):
        opt = torch.optim.Adam(self.param_groups())
        sched = decaying_lr(opt, self.hparams.lr_final_factor, self.progress)
        return [opt], [{"scheduler": sched, "interval": "step"}]

    # ------------------------------------------------------------- transport
    def transport_medium(self):
        """The medium as transport reads it: composed voxels (one lookup per query) for the
        learned medium, the ground truth itself in forward mode."""
        return self.medium.voxels() if self.learns_medium else self.medium

    def fresh_voxels(self) -> list:
        """The learned media composed anew (a graph of their own, for an objective that
        reads them after another's backward has freed the step's): one here, the medium."""
        return [self.medium.voxels()]

    def step_context(self, scenes) -> StepContext:
        """The base's context with the photos' in-scattering (:meth:`photo_source`) and the
        learned voxel media (:meth:`fresh_voxels`; none in forward mode)."""
        context = super().step_context(scenes)
        context.photo_source = self.photo_source
        context.voxels = self.fresh_voxels if self.learns_medium else None
        return context

    def photo_source(self, medium, light: ScatteredLightField):
        """:meth:`inscatter` of ``light`` as the photos read it (:meth:`photo_light`)."""
        read, coefficients_grad = self.photo_light(light)
        return self.inscatter(medium, read, coefficients_grad)

    def inscatter(self, medium, light: ScatteredLightField, coefficients_grad: bool = False):
        """In-scattering of all light for the camera rays' VRE: the first scattering of the
        sky and the known lights of ``light``'s environment (with gradients to ``medium``)
        plus the scattered light's (``light``) exact SH in-scattering (``g^l`` with gradient,
        the coefficients only with ``coefficients_grad``)."""
        s = self.hparams.samples
        sigma_t = extinction(medium)
        sky = self.illumination_of(light)

        def source(x, w, props):
            total = sky_inscatter(x, w, props.g, sigma_t, medium.bbox, sky.rest,
                                  sky.sampler, int(s["sky_env_directions"]),
                                  int(s["sky_phase_directions"]), int(s["shadow_steps"]))
            if len(sky.lights):
                total = total + direct_inscatter(x, w, props.g, sky.lights, sigma_t,
                                                 medium.bbox, int(s["shadow_steps"]), jitter=True)
            total = total + light.inscatter(x, w, props.g, trainable=coefficients_grad)
            n_dirs = int(self.coupling["unrolled_directions"])
            if n_dirs > 0 and torch.is_grad_enabled():
                total = total + unrolled_inscatter(
                    light, medium, x, w, props.g, n_dirs,
                    int(self.coupling["unrolled_samples"]))
            return total
        return source

    @torch.no_grad()
    def refresh_uncollided(self, medium, light: ScatteredLightField) -> None:
        """SH projection of the uncollided light of ``light``'s environment in ``medium`` at
        its cache points (the first refresh replaces the cache, later ones blend into it)."""
        s = self.hparams.samples
        sigma_t = extinction(medium)
        sky = self.illumination_of(light)
        pts = light.cache_points()
        chunk = int(s.get("uncollided_chunk", 2048))
        coef = torch.cat([uncollided_sh(pts[i:i + chunk], sigma_t, light.bbox,
                                        sky.rest, sky.sampler, sky.lights,
                                        light.degree, int(s["uncollided_directions"]),
                                        int(s["shadow_steps"]))
                          for i in range(0, len(pts), chunk)])
        blend = 1.0 if not self._uncollided_fresh else float(s.get("uncollided_blend", 1.0))
        light.set_uncollided(coef, blend)

    def uncollided_due(self) -> bool:
        """Whether this step refreshes the uncollided cache (first, then every
        ``samples.uncollided_every`` steps)."""
        every = int(self.hparams.samples["uncollided_every"])
        return not self._uncollided_fresh or self.global_step % every == 0

    def _update_resolution(self) -> None:
        if self.learns_medium and \
                self.medium.follow_schedule(self.progress(), self.optimizers().optimizer):
            log.info("Medium modulation resampled to %d^3 cells at step %d",
                     self.medium.resolution, self.global_step)

    # --------------------------------------------------------------- training
    def photo_light(self, light: ScatteredLightField) -> tuple[ScatteredLightField, bool]:
        """``light`` as the photo objective reads it, and whether its coefficients take
        gradient there: as it is, without; with the adjoint on, the stage's own light read
        through a leaf whose gradient becomes the adjoint's source (:meth:`adjoint_step`)."""
        if light is not self.light or self.adjoint is None:
            return light, False
        leaf = light.coefficients.detach().requires_grad_(True)
        self._photo_coefficients = leaf
        return SHGrid(leaf, light.uncollided, light.degree, light.bbox,
                      light.radiance_scale), True

    def training_step(self, batch: dict, batch_idx: int) -> torch.Tensor:
        opt = self.optimizers()
        self._update_resolution()
        medium = self.transport_medium()
        start = time.perf_counter()
        if self.uncollided_due():
            for light in self.env_lights:
                self.refresh_uncollided(detached(medium), light)
            self._uncollided_fresh = True
        self.log("time/step_uncollided_s", time.perf_counter() - start)
        opt.zero_grad(set_to_none=True)
        scenes = [(medium, light) for light in self.env_lights]
        if len(scenes) > 1:
            batch = {**batch, "scene": self.scenes_of(batch["env"])}
        total = self.backward_objectives(batch, self.step_context(scenes))
        if self._photo_coefficients is not None and self._photo_coefficients.grad is not None:
            self.adjoint_step(medium, self._photo_coefficients.grad)
        self._photo_coefficients = None
        if self.learns_medium:
            self.log("train/medium_resolution", float(self.medium.resolution))
        opt.step()
        self.lr_schedulers().step()
        return torch.as_tensor(total)

    def scenes_of(self, env: torch.Tensor) -> torch.Tensor:
        """Each ray's position among the training environments (its light field in
        :attr:`env_lights`), from its position ``env`` (B,) among the dataset's."""
        return self._scene_of_env[env.cpu()]

    def adjoint_step(self, medium, grad: torch.Tensor) -> None:
        """Fold the photo loss's gradient to the coefficient grid (``grad``) into the adjoint
        source, train the adjoint grid one step toward its equation, and backpropagate the
        medium's sensitivity through the scattered light (:mod:`nrt.losses.adjoint`)."""
        start = time.perf_counter()
        light, bbox = self.light, self.light.bbox
        cell_volume = torch.prod(bbox[1] - bbox[0]) / light.resolution ** 3
        blend = float(self.coupling["adjoint_blend"])
        self.adjoint_source.mul_(1 - blend).add_(blend * grad / cell_volume)
        q_scale = self.adjoint_source.square().mean().sqrt().clamp_min(1e-30)
        one = self.adjoint.radiance_scale
        adjoint = SHGrid(self.adjoint.coefficients, self.adjoint.uncollided, light.degree,
                         bbox, one)
        source = SHGrid(self.adjoint_source / q_scale, self.adjoint.uncollided, light.degree,
                        bbox, one)
        n = int(self.hparams.samples["transport_points"])
        pts, dirs = uniform_samples(n, bbox)
        loss = adjoint_loss(adjoint, source, detached(medium), pts, dirs,
                            int(self.hparams.samples["transport_samples"]))
        self.manual_backward(loss)
        pts = uniform_box_points(n, bbox)
        self.manual_backward(medium_sensitivity(adjoint, light.grid(), self.medium.voxels(),
                                                pts, float(q_scale)))
        self.log("train/loss_adjoint", loss.detach())
        self.log("time/step_adjoint_s", time.perf_counter() - start)

    # ------------------------------------------------------------- validation
    def predict_view(self, batch: dict) -> dict[str, torch.Tensor]:
        """:meth:`predict_pixels` of a held-out view lit by its own environment's light."""
        light = self.env_lights[int(self._scene_of_env[int(batch["env"])])]
        with torch.no_grad():
            return self.render_pixels(batch["origins"], batch["dirs"], batch["background"],
                                      self.transport_medium(), light)

    def predict_pixels(self, origins: torch.Tensor, dirs: torch.Tensor,
                       background: torch.Tensor) -> dict[str, torch.Tensor]:
        """Two predictions of ``L(o, -v)`` (R, 3) for view rays, chunked, without graph:
        ``vre`` (the photo objective's rendering, strata centres) and ``exit`` (``T E(v)``
        plus the scattered light where the ray leaves the box: the light field alone)."""
        with torch.no_grad():
            return self.render_pixels(origins, dirs, background, self.transport_medium(),
                                      self.light)

    @torch.no_grad()
    def render_pixels(self, origins: torch.Tensor, dirs: torch.Tensor, background: torch.Tensor,
                      medium, light: ScatteredLightField) -> dict[str, torch.Tensor]:
        """:meth:`predict_pixels` through ``medium`` with ``light``."""
        s, chunk = self.hparams.samples, self.hparams.eval_chunk
        out: dict[str, list] = {"vre": [], "exit": []}
        source = self.inscatter(medium, light)
        for i in range(0, len(origins), chunk):
            o, d, bg = origins[i:i + chunk], dirs[i:i + chunk], background[i:i + chunk]
            out["vre"].append(render_view_rays(medium, o, d, bg, int(s["vre_samples"]),
                                               source, jitter=False))
            scattered = exit_radiance(light, o, d, torch.zeros_like(bg))
            out["exit"].append(transmitted_background(medium, o, d, bg,
                                                      int(s["vre_samples"])) + scattered)
        return {k: torch.cat(v) for k, v in out.items()}

    # ------------------------------------------------------------------ resume
    def on_load_checkpoint(self, checkpoint: dict) -> None:
        """The baked density comes with the state (no EA field needed); the medium resizes
        its grid to the checkpoint's itself
        (:class:`~nrt.modules.fields.voxel_medium.VoxelMedium`); the light fields of more
        environments than one are built to receive theirs. The uncollided caches come
        with the state too: a resumed run refreshes them on their schedule, as the run left
        alone does, not at once."""
        super().on_load_checkpoint(checkpoint)
        self._baked = True
        self._uncollided_fresh = checkpoint.get("global_step", 0) > 0
        more = {key.split(".")[1] for key in checkpoint["state_dict"]
                if key.startswith("more_lights.")}
        self.add_lights(1 + len(more))
