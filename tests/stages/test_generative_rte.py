"""Stage 2 in generative mode (``nrt-train stage=rte mode=generative scene=family
init.ea_ckpt=<generative EA run>``) on a tiny family rendered for real, after a generative
EA run: the stage composes and starts from the EA run's codes and densities, logs every
member's property MSEs and their mean, exports valid grids per member and the codes,
decodes a valid medium from any code, resumes its codes, and at the preset each member's
own code reconstructs its own medium better than the other codes do on average; config
mistakes end in
``nrt: error:`` with status 2 before any data."""

from __future__ import annotations

import itertools
import os
import re
import subprocess
from pathlib import Path

import hydra
import lightning as L
import numpy as np
import pytest
import torch
from lightning.pytorch.callbacks import ModelCheckpoint
from omegaconf import OmegaConf

from nrt.cli.checks import check_mode
from nrt.cli.train import resolve_ea_checkpoint
from nrt.data.family import ensure_family
from nrt.data.grids import load_property_grids
from nrt.errors import ConfigError, NrtError
from nrt.evaluation.latent_gaussian import scott_bandwidth
from nrt.evaluation.sample import SampleSettings, fold
from nrt.losses.objective import scene_mean
from nrt.metrics import property_mse
from nrt.physics.phase import G_MAX
from nrt.physics.volume import cell_centres
from nrt.stages.family import SceneFamily
from nrt.stages.generative_ea import load_generative_ea
from nrt.stages.member_adam import MemberAdam, member_blocks
from nrt.stages.rte import RTEStage
from tests.conftest import (
    GENERATIVE_FAMILY,
    NRT_TRAIN,
    SMALL_FAMILY,
    compose_config,
    refusal,
    single_scene_ea_checkpoint,
)
from tests.stages.test_generative_ea import SHORT as EA_SHORT
from tests.stages.test_generative_ea import K, cli_family_run
from tests.stages.test_generative_ea import train as train_ea

pytestmark = pytest.mark.e2e

STAGE2 = ("stage=rte", *GENERATIVE_FAMILY, *SMALL_FAMILY)
SHORT = ("budget.rte.steps=24", "budget.val_every=12", "budget.val_views=1",
         "budget.checkpoint_every=24", "budget.rte.uncollided_directions=16")
"""A short in-process stage-2 run (~6 s): what is logged, exported and resumed."""
PRESET_RUN = ("budget.val_every=900", "budget.val_views=1")
"""The preset's own run (tiny family at full size, 600 EA steps, 900 stage-2 steps, one
validation at the end): the members' media told apart by their codes (slow tier, ~4 min
on 2 shared cores). On the small test family the codes do not tell every member's
medium apart (measured after 600 stage-2 steps: two of the four members were closer to
another member's reconstruction than to their own, their EA densities being 5-10x off
in scale): stage 2's convergence decides it."""


def stage2_config(family: Path, ea_ckpt: Path | None, *overrides: str, stage: str = "rte",
                  small: bool = True):
    return compose_config("train", [
        f"stage={stage}", *GENERATIVE_FAMILY, *(SMALL_FAMILY if small else ()),
        f"paths.output_dir={family.parent.parent}",
        *((f"init.ea_ckpt={ea_ckpt}",) if ea_ckpt is not None else ()), *overrides])


def train_stage2(family: Path, ea_ckpt: Path | None, checkpoint_dir: Path, *overrides: str,
                 resume: Path | None = None, stage: str = "rte", small: bool = True,
                 extra_callbacks: tuple[L.Callback, ...] = ()) -> dict:
    """A generative stage (2, or 1 with ``stage="ea"``) trained in-process on a family (the
    small test family, or with ``small=False`` the preset's) as nrt-train builds it:
    ``model``, ``dm``, ``trainer``, ``metrics`` (the last validation's) and ``ckpt`` (its
    last checkpoint)."""
    cfg = stage2_config(family, ea_ckpt, *overrides, stage=stage, small=small)
    L.seed_everything(cfg.seed, workers=True)
    model = hydra.utils.instantiate(cfg.model, _convert_="all")
    dm = hydra.utils.instantiate(cfg.data, dataset_dir=str(family))
    callbacks = [hydra.utils.instantiate(cfg.callbacks[name])
                 for name in ("held_out_metrics", "property_metrics")]
    callbacks.append(ModelCheckpoint(dirpath=checkpoint_dir, save_last=True, save_top_k=0,
                                     monitor=None,
                                     every_n_train_steps=cfg.budget.checkpoint_every))
    callbacks.extend(extra_callbacks)
    trainer = L.Trainer(max_steps=cfg.stage.steps, accelerator="cpu", logger=False,
                        enable_progress_bar=False, inference_mode=False,
                        num_sanity_val_steps=0, callbacks=callbacks)
    trainer.fit(model, datamodule=dm, ckpt_path=None if resume is None else str(resume))
    return {"model": model, "dm": dm, "cfg": cfg, "trainer": trainer,
            "ckpt": checkpoint_dir / "last.ckpt",
            "metrics": {k: float(v) for k, v in trainer.callback_metrics.items()}}


@pytest.fixture(scope="module")
def short_ea(family_dir, tmp_path_factory) -> Path:
    """The checkpoint of a short generative EA run (40 steps) on the test family."""
    return train_ea(family_dir, tmp_path_factory.mktemp("ea_short"), *EA_SHORT)["ckpt"]


@pytest.fixture(scope="module")
def short(family_dir, short_ea, tmp_path_factory) -> dict:
    return train_stage2(family_dir, short_ea, tmp_path_factory.mktemp("rte_short"), *SHORT)


@pytest.fixture(scope="module")
def trained(tmp_path_factory) -> dict:
    """The tiny preset's family rendered at full size, its generative EA run and generative
    stage 2, both at the preset's steps (:data:`PRESET_RUN`)."""
    out = tmp_path_factory.mktemp("preset_family")
    cfg = compose_config("train", [*GENERATIVE_FAMILY, f"paths.output_dir={out}"])
    family = ensure_family(OmegaConf.to_container(cfg.scene, resolve=True),
                           cfg.paths.data_dir, progress=False)
    ea = train_stage2(family, None, tmp_path_factory.mktemp("ea_preset"), "budget.val_every=300",
                      "budget.val_views=1", stage="ea", small=False)["ckpt"]
    run = train_stage2(family, ea, tmp_path_factory.mktemp("rte_preset"), *PRESET_RUN,
                       small=False)
    return {**run, "ea_ckpt": ea}


def truths(dm) -> list[dict[str, torch.Tensor]]:
    gts = dm.member_ground_truths
    assert len(gts) == K and all(gt is not None for gt in gts)
    return gts


def assert_valid(grids: dict[str, torch.Tensor], resolution: int) -> None:
    """The layout of ``Stage.property_grids``, finite, sigma >= 0, |g| < 1."""
    assert grids["sigma_a"].shape == grids["sigma_s"].shape == (resolution,) * 3 + (3,)
    assert grids["g"].shape == (resolution,) * 3
    for key, value in grids.items():
        assert value.device.type == "cpu" and not value.requires_grad, key
        assert torch.isfinite(value).all(), key
    assert (grids["sigma_a"] >= 0).all() and (grids["sigma_s"] >= 0).all()
    assert grids["g"].abs().max() <= G_MAX + 1e-6


# ------------------------------------------------------------------- config


def test_stage_composes_the_generative_components():
    cfg = compose_config("train", list(STAGE2))
    assert cfg.model._target_ == "nrt.stages.rte.RTEStage"
    assert cfg.model.scenes._target_ == "nrt.stages.family.SceneFamily"
    assert cfg.model.light_field._target_.endswith("LatentSHGridLightField")
    assert cfg.model.medium._target_.endswith("LatentVoxelMedium")
    assert cfg.model.medium.parametrization == "extinction"
    assert cfg.model.scenes.members == cfg.model.light_field.members == K
    assert cfg.model.scenes.latent_dim == cfg.model.medium.latent_dim == 4
    assert list(cfg.stage.environments) == [0]
    assert cfg.data._target_ == "nrt.data.datamodule.FamilyRayDataModule"
    check_mode(cfg)
    ea = compose_config("train", list(GENERATIVE_FAMILY))  # stage 1 is unchanged
    assert ea.model._target_.endswith("GenerativeEAModule") and ea.model.latent_dim == 4


def test_scene_mean_is_the_mean_over_all_items():
    losses = torch.rand(10)
    members = torch.tensor([0, 2, 2, 1, 0, 2, 1, 1, 1, 0])
    total = scene_mean(members, lambda k, mask: losses[mask].mean())
    assert float(total) == pytest.approx(float(losses.mean()), rel=1e-6)


# ------------------------------------------------------------------- the start


def test_the_stage_starts_from_the_ea_runs_codes_and_densities(short_ea, family_dir):
    """Built from the config, the stage holds the EA run's codes; before training (zero
    modulation), member k's medium is the EA density under z_k (sigma_t in every channel,
    evaluated independently here with the EA field) with the initial albedo."""
    cfg = stage2_config(family_dir, short_ea)
    family = hydra.utils.instantiate(cfg.model, _convert_="all").scenes
    _, field, codes, _ = load_generative_ea(str(short_ea))
    assert torch.equal(family.codes.detach(), codes)
    r = cfg.budget.rte.density_resolution
    pts = cell_centres(r, field.bbox).reshape(-1, 3)
    for k in (0, K - 1):
        grids = family.property_grids_for(codes[k], r)
        sigma_t = grids["sigma_a"] + grids["sigma_s"]
        rho = field.density(pts, codes[k]).detach().reshape(r, r, r, 1).clamp_min(0)
        assert torch.allclose(sigma_t, rho.expand_as(sigma_t), rtol=1e-5, atol=1e-6)
        albedo = grids["sigma_s"] / sigma_t.clamp_min(1e-12)
        dense = sigma_t > 1e-3
        assert torch.allclose(albedo[dense], torch.tensor(cfg.model.medium.init_albedo),
                              atol=1e-5)


# ------------------------------------------------------------------- training


def test_validation_logs_every_member_and_the_mean(short):
    metrics = short["metrics"]
    for name in ("psnr", "ssim", "mse_sigma_t_x100", "mse_sigma_a_x100", "mse_sigma_s_x100",
                 "mse_g_x100"):
        per_member = [metrics[f"val/{name}_member{k}"] for k in range(K)]
        assert all(np.isfinite(per_member)), (name, per_member)
        assert metrics[f"val/{name}"] == pytest.approx(np.mean(per_member), rel=1e-5)
    assert metrics["val/psnr"] > metrics["val/psnr_background_only"]
    family = short["model"].scenes  # the logged MSE is the member's own code's
    gt = truths(short["dm"])[2]
    own = property_mse(family.property_grids_for(family.codes[2], gt["g"].shape[0]), gt)
    assert metrics["val/mse_sigma_t_x100_member2"] == pytest.approx(float(own["sigma_t"]),
                                                                     rel=1e-4)


def test_export_writes_member_grids_and_codes(short, tmp_path):
    model = short["model"]
    family = model.scenes
    exports = model.export(tmp_path)
    names = [f"family_seed{k}" for k in range(K)]
    assert family.member_names() == names
    with np.load(exports["latents"]) as latents:
        assert np.array_equal(latents["codes"], family.codes.detach().numpy())
        assert list(latents["names"]) == names and list(latents["seeds"]) == list(range(K))
    for k, name in enumerate(names):
        path = tmp_path / "members" / name / "medium_grids.npz"
        assert exports[f"medium_grids_{name}"] == str(path)
        grids = load_property_grids(path)  # validates layout and finiteness
        assert torch.equal(grids["bbox"], model.medium_bbox())
        assert_valid({k: v for k, v in grids.items() if k != "bbox"}, 32)  # the truth's grid
        expected = family.property_grids_for(family.codes[k], 32)
        for key in ("sigma_a", "sigma_s", "g"):
            assert torch.equal(grids[key], expected[key]), key


def test_any_code_decodes_a_valid_medium(short):
    """The contract's ``property_grids_for``: finite, non-negative, |g| < 1, on the CPU and
    without gradient, for codes near the learned ones and far from them."""
    model = short["model"]
    family = model.scenes
    torch.manual_seed(0)
    for code in (family.codes[0], torch.zeros(4), torch.randn(4), 30 * torch.randn(4)):
        assert_valid(family.property_grids_for(code, 12), 12)
    assert model.property_grids(12) is None  # one medium per member, not one


def test_one_decode_a_step_gives_the_gradients_of_one_decode_per_objective(short):
    """The step decodes each member's medium once, hands the objectives leaves and carries
    their gradients back through the decoders in one backward (``SceneFamily.pairs``,
    ``backward_media``). Every parameter's gradient equals the chain rule taken the direct
    way: each objective on media decoded for it, summed, one backward. The two sum the
    same float32 terms in another order, so they agree to rounding (rtol 1e-4 of each
    gradient's largest entry, against gradients that differ between members and steps by
    order 1)."""
    model, family = short["model"], short["model"].scenes
    batch = next(iter(short["dm"].train_dataloader()))
    weights = model.active_weights()
    assert {"photo", "transport", "extinction_prior"} <= set(weights)  # all read the media
    params = [p for p in model.parameters() if p.requires_grad]

    def gradients(step) -> list[torch.Tensor]:
        model.zero_grad(set_to_none=True)
        torch.manual_seed(7)  # the objectives draw the same samples both ways
        step()
        return [torch.zeros_like(p) if p.grad is None else p.grad.clone() for p in params]

    def once_a_step():
        scenes = family.pairs(batch)
        context = model.step_context(scenes)
        for name, weight in weights.items():
            (weight * model.objectives[name].loss({**batch, "scene": batch["member"]},
                                                   context)).backward()
        family.backward_media(torch.Tensor.backward)

    def direct():
        scenes = [family.member_scene(k) for k in range(K)]
        context = model.step_context(scenes)
        context.voxels = lambda: [family.member_medium(k) for k in range(K)]
        sum(weight * model.objectives[name].loss({**batch, "scene": batch["member"]}, context)
            for name, weight in weights.items()).backward()

    ours = gradients(once_a_step)
    assert not family._decoded  # the step's media are let go
    reference = gradients(direct)
    codes = next(i for i, p in enumerate(params) if p is family.codes)
    assert ours[codes].abs().max() > 0  # the photos reach the codes through the leaves
    for a, b in zip(ours, reference, strict=True):
        assert torch.allclose(a, b, rtol=1e-4, atol=1e-4 * float(b.abs().max()) + 1e-12)


def test_noisy_codes_decode_the_step_around_each_code(short):
    """``code_noise`` h: a step decodes member k's medium at ``z_k + h s eps`` (s the codes'
    spread per dimension, eps a fresh normal draw per member and step), its light at z_k;
    the photos' gradient still reaches the codes; h = 0 decodes at the codes bit for bit."""
    family = short["model"].scenes
    batch = next(iter(short["dm"].train_dataloader()))
    try:
        plain = [leaf.stacked for leaf, _ in family.pairs(batch)]
        family._decoded = []
        for k, stacked in enumerate(plain):
            assert torch.equal(stacked, family.member_medium(k).stacked.detach())
        family.code_noise = 0.5
        torch.manual_seed(11)
        eps = torch.randn(K, family.codes.shape[1])
        expected = family.codes.detach() + 0.5 * family.codes.detach().std(0) * eps
        torch.manual_seed(11)
        pairs = family.pairs(batch)
        for k, (leaf, light) in enumerate(pairs):
            assert torch.allclose(leaf.stacked, family.member_medium(k, expected[k])
                                  .stacked.detach(), rtol=1e-6, atol=1e-7)
            assert not torch.allclose(leaf.stacked, plain[k])  # another medium than at z_k
            at_code = family.light.member(k, family.codes[k].detach())
            assert torch.equal(light.coefficients, at_code.coefficients)  # the light at z_k
        family.codes.grad = None
        sum(leaf.stacked.sum() for leaf, _ in pairs).backward()
        family.backward_media(torch.Tensor.backward)
        assert family.codes.grad is not None and family.codes.grad.abs().max() > 0
        second = family.pairs(batch)  # a fresh draw each step
        assert not torch.equal(second[0][0].stacked, pairs[0][0].stacked)
    finally:
        family.code_noise, family._decoded, family.codes.grad = 0.0, [], None


@pytest.mark.parametrize("value, match", [(-0.5, "must be a number >= 0"),
                                          (True, "must be a number >= 0")])
def test_bad_code_noise_is_refused(short, value, match):
    from nrt.stages.family import SceneFamily

    with pytest.raises(ConfigError, match=match):
        SceneFamily(short["model"], members=K, latent_dim=4, code_noise=value,
                    ea_field={}, member_info=None)


def test_folding_a_run_without_offsets_is_refused(short):
    """``nrt-sample fold.steps>0`` on a run trained without member offsets: a config error
    naming the key and the fix, and the decoder left as it was."""
    family = short["model"].scenes
    assert not family.holds_member_offsets  # fold.steps=auto leaves it unfolded
    values = family.medium.modulation.values.detach().clone()
    with pytest.raises(ConfigError, match=re.escape("Sample it with fold.steps=0")):
        family.fold_offsets(steps=5, lr=0.02)
    assert torch.equal(family.medium.modulation.values, values)


def test_folding_members_without_density_is_refused(short, monkeypatch):
    """``nrt-sample fold.steps>0`` on a run whose members have no density on any cell (an
    empty EA density under every code): a config error naming the key and the fix, before
    any fit."""
    family = short["model"].scenes
    monkeypatch.setattr(type(family.medium), "member_offsets", property(lambda self: 4))
    monkeypatch.setattr(family, "density_for", lambda code: torch.zeros(4, 4, 4, 1))
    with pytest.raises(ConfigError, match="no member of this run has density"):
        family.fold_offsets(steps=5, lr=0.02)


def test_a_step_of_some_members_concerns_those_members_only(short):
    """With batches of some members (``step_members``), a step decodes their media and
    lights alone, maps each ray to its member's place among them, takes the codes' prior
    over them, counts their steps and refreshes each member's uncollided light every
    ``uncollided_every`` of its own steps, its first refresh replacing the cache."""
    model, family = short["model"], short["model"].scenes
    saved = family.member_steps.clone()
    try:
        family.member_steps.zero_()
        step = torch.tensor([1, 3])
        batch = {"member": torch.tensor([3, 1, 1, 3, 3]), "step_members": step}
        pairs = family.pairs(batch)
        assert len(pairs) == 2 and len(family.fresh_voxels()) == 2
        assert family.scene_of(batch).tolist() == [1, 0, 0, 1, 1]
        expected = family.latent_prior_weight * family.codes[step].square().sum(-1).mean()
        assert torch.equal(family.priors()["latent_prior"], expected)
        assert family.uncollided_due(model.uncollided, 5) == [(0, True), (1, True)]
        assert family.member_steps.tolist() == [0, 1, 0, 1]
        every = model.uncollided.every
        due = []  # per step: member -> whether it is its first refresh
        for n in range(2 * every):  # member 3 every step, member 0 every other step
            chosen = torch.tensor([0, 3]) if n % 2 else torch.tensor([3])
            family.pairs({"member": chosen, "step_members": chosen})
            due.append({int(chosen[i]): first
                        for i, first in family.uncollided_due(model.uncollided, 0)})
        # member 3 has had one step before: its own steps `every` and 2 `every` refresh
        assert [n for n, d in enumerate(due) if 3 in d] == [every - 1, 2 * every - 1]
        assert [(n, d[0]) for n, d in enumerate(due) if 0 in d] == [(1, True)]
        assert family.member_steps.tolist() == [every, 1, 0, 1 + 2 * every]
    finally:
        family.member_steps.copy_(saved)
        family._step, family._decoded = None, []


def test_a_run_of_two_members_a_step_trains_every_member(family_dir, short_ea, tmp_path):
    """``data.members_per_step=2`` on the four-member family: every step decodes two, each
    member is drawn, every code moves and every member is validated."""
    run = train_stage2(family_dir, short_ea, tmp_path, *SHORT, "data.members_per_step=2")
    family = run["model"].scenes
    assert family.member_steps.sum() == 2 * run["cfg"].stage.steps
    assert (family.member_steps > 0).all()
    start = load_generative_ea(str(short_ea))[2]
    assert ((family.codes.detach() - start).norm(dim=-1) > 0).all()
    assert all(f"val/psnr_member{k}" in run["metrics"] for k in range(K))


class RecordShares(L.Callback):
    """Per training step, the medium's and the codes' rates as shares of their configured
    rates (the decay and any ramp)."""

    def __init__(self):
        self.shares: list[tuple[float, float]] = []

    def on_train_batch_start(self, trainer, pl_module, batch, batch_idx):
        groups = trainer.optimizers[0].param_groups
        codes = next(g for g in groups if g["params"] == [pl_module.scenes.codes])
        medium = next(g for g in groups if g.get("ramps_in") and g is not codes)
        self.shares.append((medium["lr"] / medium["initial_lr"],
                            codes["lr"] / codes["initial_lr"]))


def test_the_codes_rate_ramps_in_with_the_mediums(family_dir, short_ea, tmp_path):
    """``model.medium_rampup``: each member's density follows its code, so the codes' rate
    ramps in with the medium's (0 through the light's warm-up, then rising to the decayed
    rate), rather than taking full-rate Adam steps on fresh moments when the photos start."""
    record = RecordShares()
    train_stage2(family_dir, short_ea, tmp_path, *SHORT, "budget.rte.light_warmup=0.25",
                 "model.medium_rampup=0.5", "model.lr_final_factor=1",  # no decay: the ramp alone
                 extra_callbacks=(record,))
    medium, codes = zip(*record.shares, strict=True)
    assert codes == pytest.approx(medium, rel=1e-9)
    assert codes[0] == 0.0 and list(codes) == sorted(codes) and codes[-1] == 1.0, codes
    assert sum(0 < c < 1 for c in codes) >= 5, codes


@pytest.mark.slow  # a training of its own (~40 s on 2 shared cores); the unit test of the
# offsets (tests/modules/fields/test_voxel_medium.py) stays in the fast tier
def test_member_offsets_train_each_member_and_survive_a_checkpoint(family_dir, short_ea,
                                                                    tmp_path):
    """``mode.latent.member_offsets=true``: each member's medium reads its own feature
    offset, zero at the start (so the start is the code's medium), resampled with the
    shared features on the coarse-to-fine schedule, moved by its member's steps only and
    pulled toward zero by the logged ``offset_prior``. Validation and export score the
    member's medium with its offset, a new code decodes without one, and a checkpoint
    written at the final resolution reloads the offsets exactly; folding them into the
    shared decoder brings the codes alone closer to the members' media. With
    ``light_offsets=true`` each member's light reads its own offset too."""
    overrides = (*SHORT, "mode.latent.member_offsets=true", "mode.latent.light_offsets=true",
                 "data.members_per_step=2")
    fresh = hydra.utils.instantiate(stage2_config(family_dir, short_ea, *overrides).model,
                                    _convert_="all").scenes
    assert fresh.medium.member_offsets == K
    assert not fresh.medium.modulation.offsets.any()  # the start: each code's own medium
    run = train_stage2(family_dir, short_ea, tmp_path, *overrides)
    family = run["model"].scenes
    decoder = family.medium.modulation
    r = family.medium.resolution
    assert r > fresh.medium.resolution  # the schedule doubled the grid ...
    assert decoder.offsets.shape == (r, r, r, K * decoder.features)  # ... and the offsets
    assert (family.member_steps > 0).all()
    for k in range(K):  # every member was drawn, so its offset moved
        assert decoder.member_offset(k).abs().max() > 0, k
        own = family.member_property_grids(k, 16)["sigma_s"]
        assert not torch.equal(own, family.property_grids_for(family.codes[k], 16)["sigma_s"])
    assert run["metrics"]["train/offset_prior"] > 0
    light = run["model"].light
    for k in range(K):  # each member's light reads its own moved offset
        assert light.decoder.member_offset(k).abs().max() > 0, k
        code = family.codes[k].detach()
        assert not torch.equal(light.member(k, code).coefficients, light.decode(code))
    family._step = None  # the prior over every member, not the last step's
    expected = family.offset_prior_weight * decoder.offsets.detach().square().mean() \
        * decoder.features
    assert float(family.priors()["offset_prior"].detach()) == pytest.approx(float(expected),
                                                                           rel=1e-5)
    gt = truths(run["dm"])[1]
    own = property_mse(family.member_property_grids(1, gt["g"].shape[0]), gt)
    assert run["metrics"]["val/mse_sigma_t_x100_member1"] == pytest.approx(
        float(own["sigma_t"]), rel=1e-4)
    loaded = RTEStage.load_from_checkpoint(run["ckpt"], map_location="cpu").scenes
    assert torch.equal(loaded.medium.modulation.offsets, decoder.offsets.detach())
    for key, value in loaded.member_property_grids(2, 16).items():
        assert torch.equal(value, family.member_property_grids(2, 16)[key]), key
    # folding the offsets into the shared decoder (what nrt-sample's fold.steps does):
    # the codes alone then decode closer to the members' media than before, with no offsets
    def sigma_t(grids: dict) -> torch.Tensor:
        return grids["sigma_a"] + grids["sigma_s"]

    before = [sigma_t(family.member_property_grids(k, 16)) for k in range(K)]
    unfolded = [float((sigma_t(family.property_grids_for(family.codes[k], 16)) - before[k])
                      .square().mean()) for k in range(K)]
    assert loaded.holds_member_offsets  # so nrt-sample's fold.steps=auto folds it
    plain = loaded.fold_offsets(steps=100, lr=1e-3)  # offsets 24 steps old: a small rate
    assert plain["fold_end"] < plain["fold_start"] and plain["fold_steps"] == 100
    assert not loaded.medium.modulation.offsets.any()
    folded = [float((sigma_t(loaded.member_property_grids(k, 16)) - before[k])
                    .square().mean()) for k in range(K)]
    assert np.mean(folded) < np.mean(unfolded), (folded, unfolded)
    # nrt-sample's fold with fold.bandwidth=scott: its objective (at the codes and at draws
    # around them) falls, and it keeps no offsets
    around = RTEStage.load_from_checkpoint(run["ckpt"], map_location="cpu").scenes
    settings = SampleSettings(fold_steps=100, fold_lr=1e-3, fold_bandwidth="scott")
    figures = fold(around, settings)
    assert figures["fold_bandwidth"] == scott_bandwidth(*around.codes.shape)
    assert figures["fold_end"] < figures["fold_start"]
    assert not around.medium.modulation.offsets.any()


class UndrawnMembers(L.Callback):
    """Per step: the drawn members, whether every undrawn member's code and medium and
    light offsets kept their values exactly, and whether a drawn one's moved (steps where
    the coarse-to-fine schedule resamples the offsets left out)."""

    def __init__(self):
        self.steps: list[tuple[list[int], bool, bool]] = []

    def values(self, stage) -> list[torch.Tensor]:
        family = stage.scenes
        return [family.codes.detach().clone(),
                *(member_blocks(p.detach(), K, -1).clone()
                  for p in (*family.medium.member_blocks(), *family.light.member_blocks()))]

    def on_train_batch_start(self, trainer, stage, batch, batch_idx):
        self._before = self.values(stage)
        self._drawn = batch["step_members"].tolist()

    def on_train_batch_end(self, trainer, stage, outputs, batch, batch_idx):
        after = self.values(stage)
        if [a.shape for a in after] != [b.shape for b in self._before]:
            return  # the coarse-to-fine schedule resampled every offset this step
        undrawn = [k for k in range(K) if k not in self._drawn]
        kept = all(torch.equal(a[undrawn], b[undrawn]) for a, b in zip(after, self._before,
                                                                        strict=True))
        moved = any(not torch.equal(a[self._drawn], b[self._drawn])
                    for a, b in zip(after, self._before, strict=True))
        self.steps.append((self._drawn, kept, moved))


@pytest.mark.slow  # a training of its own (~30 s on 2 shared cores); MemberAdam's own tests
# (tests/stages/test_member_adam.py) stay in the fast tier
@pytest.mark.parametrize("per_member", [True, False])
def test_per_member_adam_leaves_undrawn_members_alone(family_dir, short_ea, tmp_path,
                                                      per_member):
    """``mode.latent.per_member_adam=true`` with two members a step: a step leaves every
    member it did not draw exactly as it was (code, medium and light offsets) and moves
    the ones it drew; plain Adam (false, the default) moves undrawn members too, by the
    momentum of their last draw."""
    record = UndrawnMembers()
    run = train_stage2(family_dir, short_ea, tmp_path, *SHORT,
                       "mode.latent.member_offsets=true", "mode.latent.light_offsets=true",
                       "data.members_per_step=2", f"mode.latent.per_member_adam={per_member}",
                       extra_callbacks=(record,))
    optimiser = run["trainer"].optimizers[0]
    assert isinstance(optimiser, MemberAdam) == per_member
    trained = [(kept, moved) for _, kept, moved in record.steps if moved]
    assert len(trained) >= 12, record.steps  # the photo objective acts after the warm-up
    if per_member:
        assert all(kept for kept, _ in trained), record.steps
        codes_steps = optimiser.state[run["model"].scenes.codes]["step"]
        assert 0 < codes_steps.sum() <= 2 * len(record.steps)
    else:
        assert not all(kept for kept, _ in trained), record.steps


def test_resume_continues_the_codes(short, family_dir, short_ea, tmp_path):
    """A run resumed from the checkpoint continues from its codes (not the EA run's) and
    the codes' optimiser group."""
    saved = torch.load(short["ckpt"], weights_only=True, map_location="cpu")
    assert saved["global_step"] == short["cfg"].stage.steps
    start = load_generative_ea(str(short_ea))[2]
    assert not torch.equal(saved["state_dict"]["scenes.codes"], start)  # the codes moved
    resumed = train_stage2(family_dir, short_ea, tmp_path, *SHORT, "budget.rte.steps=26",
                           resume=short["ckpt"])
    family = resumed["model"].scenes
    groups = resumed["trainer"].optimizers[0].param_groups
    assert groups[-1]["params"] == [family.codes] and groups[-1]["weight_decay"] == 0.0
    moved = (family.codes.detach() - saved["state_dict"]["scenes.codes"]).norm(dim=-1)
    assert 0 < moved.max() < 0.05, moved  # two steps on from the checkpoint's codes
    loaded = RTEStage.load_from_checkpoint(short["ckpt"], map_location="cpu").scenes
    assert torch.equal(loaded.codes.detach(), saved["state_dict"]["scenes.codes"])
    assert loaded.member_names() == [f"family_seed{k}" for k in range(K)]


def test_a_resume_that_regroups_the_optimiser_is_refused(short, family_dir, short_ea,
                                                         tmp_path):
    """Resuming the short run with per-member Adam switched on would load plain Adam's
    moments into groups that step per member (the codes' group: one parameter, now per
    member): refused before a step, with the layouts of both."""
    with pytest.raises(NrtError) as refused:
        train_stage2(family_dir, short_ea, tmp_path, *SHORT, "budget.rte.steps=26",
                     "mode.latent.per_member_adam=true", resume=short["ckpt"])
    message = str(refused.value)
    assert str(short["ckpt"]) in message
    assert "(1, False)]]" in message and "(1, True)]]" in message, message
    assert not (tmp_path / "last.ckpt").exists()  # no step was taken, nothing saved


@pytest.mark.slow
def test_codes_differ_per_member(trained):
    codes = trained["model"].scenes.codes.detach()
    start = load_generative_ea(str(trained["ea_ckpt"]))[2]
    gaps = [float((codes[i] - codes[j]).norm()) for i, j in itertools.combinations(range(K), 2)]
    start_gaps = [float((start[i] - start[j]).norm())
                  for i, j in itertools.combinations(range(K), 2)]
    # The EA run leaves the codes 0.2 or more apart; stage 2 moves them a little (its
    # photos move them, its prior pulls them in) and keeps them apart.
    assert min(gaps) > 0.5 * min(start_gaps), (gaps, start_gaps)
    assert float((codes - start).norm(dim=-1).max()) > 1e-3


@pytest.mark.slow
def test_the_familys_mean_falls_and_no_member_ends_far_above_its_start(trained):
    """Each member's sigma_t MSE against its own truth, at the start (the EA density under its
    code, zero modulation: the stage as built from the config) and at the end of the
    preset's run. Measured from the default stage 1 (the code beside the features, twice
    the steps), end / start per member: this in-process run 0.98, 0.49, 0.96, 0.67; two
    CLI runs (seeds 0, 1; docs/data/generative_stage2.csv) 1.16 / 0.98, 0.57 / 0.72,
    0.89 / 0.93, 0.73 / 0.54; three CLI runs on another machine (seeds 0-2,
    docs/data/generative_stage2_tiny.csv) 0.99 / 1.14 / 0.85, 0.63 / 0.69 / 0.89,
    0.82 / 0.87 / 0.68, 0.75 / 0.38 / 0.74. The family's mean ended at 0.60, 0.69, 0.71,
    0.70, 0.63 and 0.81 of its start: mean 0.69, standard deviation 0.07. From that start
    stage 2 does not take every member below it (member 0 starts at 14-19 and ends at
    0.85-1.16x, wandering by up to 9 % between validations: docs/generative.md). The test asks
    the family's mean for below 0.9 of its start (three deviations above the six runs'
    mean) and every member for below 1.3x its start (the worst, 1.16, plus a member's
    move of about 10 % between runs): stage 2 may not improve a member that starts well,
    but it must not lose one (a decoder that re-bakes the density without gradient takes
    a member from 58 to 1379)."""
    start = hydra.utils.instantiate(trained["cfg"].model, _convert_="all").scenes
    end = trained["model"].scenes
    before, after = [], []
    for k, gt in enumerate(truths(trained["dm"])):
        res = gt["g"].shape[0]
        for family, into in ((start, before), (end, after)):
            grids = family.property_grids_for(family.codes[k], res)
            into.append(float(property_mse(grids, gt)["sigma_t"]))
    ratios = [a / b for a, b in zip(after, before, strict=True)]
    assert np.mean(after) < 0.9 * np.mean(before), (before, after)
    assert max(ratios) < 1.3, (ratios, before, after)


def cross_table(family: SceneFamily, gts: list[dict]) -> torch.Tensor:
    """sigma_t MSE x100 (K, K) of member i's ground truth against the medium decoded from
    code j (rows i, columns j)."""
    table = torch.zeros(K, K)
    for i, j in itertools.product(range(K), range(K)):
        grids = family.property_grids_for(family.codes[j], gts[i]["g"].shape[0])
        table[i, j] = property_mse(grids, gts[i])["sigma_t"]
    return table


@pytest.mark.slow
def test_each_members_own_code_beats_the_other_codes_on_average(trained):
    """Member i's medium decoded from every code j, scored against member i's ground truth.

    Measured at the preset (three runs; docs/generative.md): the own code was
    the best of every row in two CLI runs (seeds 0 and 1, own/next-best 0.34-0.92) but of
    three rows only in this in-process run, whose member 0 came second to the code of
    member 2, its near twin (31.4 against 26.0; their true media differ by 52): the strict
    reading is not robust at this preset yet. Against the mean of the other codes the own
    code scored 0.24-0.69 of it in all three runs, while the EA start fails that for member
    1 (3.0: its density several times too dense). A change in the last bit of the
    compositing's final transmittance (tried, not kept) gave member 1 106.6 against
    the others' mean 132.4 (0.805): a single row's ratio moves by ~0.1 with float
    rounding, which differs between machines. The test asks every row for own < the
    others' mean ("better than another scene's", with the worst row measured 0.805) and the
    rows' mean ratio for < 0.6 (measured: rows 0.37, 0.75, 0.19, 0.24, mean 0.39; a row
    moving by 0.1 moves the mean by 0.025); the result follows stage 2's convergence on
    each member."""
    table = cross_table(trained["model"].scenes, truths(trained["dm"]))
    ratios = []
    for i in range(K):
        others = torch.cat((table[i, :i], table[i, i + 1:]))
        ratios.append(float(table[i, i] / others.mean()))
    assert max(ratios) < 1.0 and np.mean(ratios) < 0.6, (ratios, table)


# -------------------------------------------------------------- config errors


@pytest.mark.parametrize("overrides, message", [
    (("stage=forward",), "built for stage=ea and stage=rte"),
    (("stage=dpt",), "built for stage=ea and stage=rte"),
    (("stage=rte", "experiment=rte_paper"), "single-scene formulation"),
])
def test_bad_stages_are_refused_from_the_config(overrides, message):
    cfg = compose_config("train", [*GENERATIVE_FAMILY, *overrides])
    with pytest.raises(ConfigError, match=re.escape(message)):
        check_mode(cfg)


def test_bad_starts_are_refused_before_any_data(tmp_path, short_ea, family_dir):
    """In-process, as nrt-train meets them before loading data: no generative EA run to
    start from, a single-scene EA checkpoint, codes of another dimension."""
    empty = compose_config("train", [*STAGE2, f"paths.output_dir={tmp_path}"])
    with pytest.raises(NrtError, match="no EA run under"):
        resolve_ea_checkpoint(empty)
    single = single_scene_ea_checkpoint(tmp_path / "single.ckpt")
    for ckpt, overrides, message in ((single, (), "is a single-scene EA run"),
                                     (short_ea, ("mode.latent.dim=3",), "mode.latent.dim=3")):
        cfg = stage2_config(family_dir, ckpt, *overrides)
        with pytest.raises(Exception, match=re.escape(message)):
            hydra.utils.instantiate(cfg.model, _convert_="all")


# The same refusal is checked in-process in the fast tier; this one starts a process.
@pytest.mark.slow
def test_a_single_scene_checkpoint_exits_2_before_any_data(tmp_path):
    """Through the real CLI: one ``nrt: error:`` paragraph, status 2, nothing rendered and
    no run folder left behind."""
    single = single_scene_ea_checkpoint(tmp_path / "single.ckpt")
    out = tmp_path / "out"
    out.mkdir()
    env = {k: v for k, v in os.environ.items() if k != "HYDRA_FULL_ERROR"}
    proc = subprocess.run([*NRT_TRAIN, *STAGE2, f"init.ea_ckpt={single}"],
                          env={**env, "NRT_OUTPUT_DIR": str(out)}, capture_output=True,
                          text=True, timeout=300)
    assert "is a single-scene EA run" in refusal(proc.returncode, proc.stderr)
    assert list(out.iterdir()) == []  # nothing rendered, no run folder


# -------------------------------------------------------------- the CLI end to end


@pytest.mark.slow
def test_cli_trains_stage_2_on_a_family_and_resumes_in_place(family_dir, short_ea):
    """``nrt-train stage=rte mode=generative scene=family init.ea_ckpt=...``: run.json, the
    per-member metrics, the exports; ``resume=true`` continues the run in place; the
    checkpoint loads by the class run.json's config names, as every run does."""
    args = (*GENERATIVE_FAMILY[1:], *SMALL_FAMILY, f"init.ea_ckpt={short_ea}",
            "budget.val_every=10", "budget.val_views=1", "budget.checkpoint_every=10",
            "budget.rte.uncollided_directions=16")
    run, info, saved = cli_family_run(family_dir, "rte", args, (20, 30),
                                      ("mse_sigma_t_x100", "psnr"), "medium_grids.npz",
                                      codes_key="scenes.codes")
    assert info["ea_ckpt"] == str(short_ea.resolve())
    target = hydra.utils.get_class(OmegaConf.load(run / ".hydra" / "config.yaml").model._target_)
    family = target.load_from_checkpoint(run / "checkpoints" / "last.ckpt",
                                         map_location="cpu").scenes
    assert family.member_names() == [f"family_seed{k}" for k in range(K)]
    assert torch.equal(family.codes.detach(), saved["state_dict"]["scenes.codes"])
