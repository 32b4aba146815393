"""Stage 2 (the default, split formulation) end to end: forward mode against Mitsuba's
photos, ``stage=ea`` then ``stage=rte`` through the real CLI with the medium improving on
its EA start, resume at the reached resolution, the terms a scene's effects switch on and
off, and hard cases that must never put NaN or Inf anywhere."""

from __future__ import annotations

import json

import lightning as L
import numpy as np
import pytest
import torch
from hydra.errors import InstantiationException
from omegaconf import OmegaConf

from nrt.errors import ConfigError, DatasetError
from nrt.losses.extinction_tv import total_variation
from nrt.modules.fields.voxel_medium import VoxelMedium
from nrt.stages import rte as rte_split
from nrt.stages.rte import RTEStage
from tests.conftest import last_value, only_run_dir, read_csv_metrics, run_train, values
from tests.finite_training import fit
from tests.stages import stage2_cases as cases

pytestmark = pytest.mark.e2e

PROPERTIES = ("sigma_a", "sigma_s", "sigma_t", "g")

FORWARD_PSNR_MIN = 33.5
"""Held-out PSNR (dB, log tonemap, the preset's 2 validation views) that forward mode must
reach on the tiny default scene in 300 steps; measured: see
:func:`test_forward_mode_reproduces_the_photos`."""


@pytest.mark.slow
def test_forward_mode_reproduces_the_photos(tmp_path, tiny_dataset):
    """Forward mode: the true medium, only the scattered light learns (transport objective,
    no photos). The photo objective's image of the held-out views must reproduce Mitsuba's
    photos to :data:`FORWARD_PSNR_MIN` dB and beat the no-scattering prediction ``T E(v)``
    by > 6 dB. Measured (300 steps, seeds 0-2): 34.79-34.86 dB against 25.40
    dB for ``T E(v)``, 25.72 dB for the background alone and 26.8 dB for the first
    scattering without learned light (measured once, 4 test views), so the bound needs the
    scattered light, with a margin of ~20 times the seeds' spread (0.07 dB). The exit
    prediction (``T E(v)`` plus the light field where the rays leave the box) reached
    28.61-28.71 dB; > 2 dB over ``T E(v)`` is asserted. The paper's formulation reaches
    33.4-33.8 dB and an exit PSNR of 20-21.7 dB on this scene (test_rte_paper_stage.py)."""
    proc = run_train(tmp_path, tiny_dataset.parent, "budget.rte.steps=300", stage="forward")
    assert proc.returncode == 0, proc.stderr[-3000:]
    rows = read_csv_metrics(only_run_dir(tmp_path, "forward"))
    ours = last_value(rows, "val/psnr")
    transmitted = last_value(rows, "val/psnr_transmitted_only")
    assert ours > FORWARD_PSNR_MIN and ours > transmitted + 6.0, (ours, transmitted)
    assert last_value(rows, "val/psnr_exit") > transmitted + 2.0
    assert "val/mse_sigma_t_x100" not in rows[0]  # the medium is not learned: no such metric
    assert values(rows, "train/loss_transport") and not values(rows, "train/loss_photo")


@pytest.mark.slow  # ~60 s after the session's EA run
def test_rte_after_ea_via_cli_improves_the_medium(tiny_ea_run, tiny_dataset):
    """``stage=ea`` then ``stage=rte`` through the CLI: stage 2 finds the EA checkpoint
    itself and says so, logs the time and loss of each objective and the property MSEs from
    step 0, and moves the medium toward the truth. Measured at the tiny preset (two
    training skies, the extinction prior, 900 steps, stage-2 seeds 0-2 from one EA run):
    end/start MSE sigma_t 0.523-0.539 (18.70 -> 9.78-10.07), sigma_a 0.31-0.32, g 0.05-0.10,
    held-out PSNR 35.40-35.44 dB. The seeds spread by 0.016 in the sigma_t ratio, so the
    bound 0.6 lies four spreads above the worst seed and under two thirds (the target: an
    improvement by at least a third). Without the prior the same
    runs ended at 0.498-0.510, under one sky at 0.80-0.81 (docs/stage2.md, "Several skies",
    "Dense cores")."""
    out, ea = tiny_ea_run
    assert ea.returncode == 0, ea.stderr[-3000:]
    ea_ckpt = only_run_dir(out, "ea") / "checkpoints" / "last.ckpt"
    proc = run_train(out, tiny_dataset.parent, stage="rte")
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert f"Stage rte starts from EA checkpoint {ea_ckpt}" in proc.stdout + proc.stderr
    run = only_run_dir(out, "rte")
    # the checkpoint it found is recorded, as an absolute path, where users look for it
    assert json.loads((run / "run.json").read_text())["ea_ckpt"] == str(ea_ckpt.resolve())
    assert OmegaConf.load(run / ".hydra" / "config.yaml").init.ea_ckpt == str(ea_ckpt.resolve())
    rows = read_csv_metrics(run)
    for name in ("photo", "transport"):
        assert values(rows, f"time/step_{name}_s") and values(rows, f"train/loss_{name}")
    assert [float(r["step"]) for r in rows if r.get("val/mse_g_x100")][0] == 0
    ratio = {k: last_value(rows, f"val/mse_{k}_x100") / values(rows, f"val/mse_{k}_x100")[0]
             for k in PROPERTIES}
    assert ratio["sigma_t"] < SIGMA_T_RATIO_MAX and ratio["sigma_a"] < 0.6 and \
        ratio["g"] < 0.5, ratio
    assert last_value(rows, "val/psnr") > 33.0, last_value(rows, "val/psnr")
    assert values(rows, "train/medium_resolution")[-1] == 16  # coarse to fine: 4 -> 8 -> 16
    with np.load(run / "medium_grids.npz") as grids:
        assert grids["sigma_a"].shape == grids["sigma_s"].shape == (32, 32, 32, 3)
        assert all(np.isfinite(grids[k]).all() for k in ("sigma_a", "sigma_s", "g"))
    module = RTEStage.load_from_checkpoint(run / "checkpoints" / "last.ckpt")
    assert module.medium.resolution == 16  # the checkpoint holds the reached resolution
    grids = module.property_grids(32)
    with np.load(run / "medium_grids.npz") as exported:
        np.testing.assert_allclose(grids["sigma_s"].numpy(), exported["sigma_s"], rtol=1e-5,
                                   atol=1e-6)


SIGMA_T_RATIO_MAX = 0.6
"""End/start sigma_t MSE of the tiny CLI run; measured: see the test's docstring."""


# ------------------------------------------------------------------ in-process helpers
SMALL = ["budget.rte.rays_per_batch=128", "budget.rte.photo_rays=64",
         "budget.rte.vre_samples=12", "budget.rte.transport_points=256",
         "budget.rte.uncollided_directions=16", "budget.rte.light_resolution=6",
         "budget.rte.density_resolution=8"]


def build(tmp_path, *overrides: str, stage: str = "rte"):
    from tests.stages.test_rte_paper_stage import build as build_any

    return build_any(tmp_path, *SMALL, *overrides, stage=stage, paper=False)


@pytest.mark.parametrize("case", [*cases.HARD_CASES, "sun_1e4"])
def test_hard_cases_train_without_nonfinite_values(tmp_path, case):
    model, dm = build(tmp_path, f"scene.name={case}", "budget.rte.light_warmup=0.1",
                      *cases.hard_case_overrides(case, tmp_path))
    cases.trains_finite(model, dm, 100)


@pytest.mark.parametrize("stage", ["rte", "forward"])
def test_grey_isotropic_scene_builds_one_band_and_one_extinction_channel(tmp_path, stage):
    """``scene=isotropic``: grey extinction (one sigma_t channel, RGB albedo) and an
    isotropic phase, whose in-scattering reads SH band 0 only, so the light field holds
    band 0 alone; 20 steps run with finite values."""
    model, dm = build(tmp_path, "scene=isotropic", stage=stage)
    assert model.light.degree == 0 and model.light.coefficients.shape[-1] == 3
    fit(model, dm, 20)
    props = model.medium(torch.rand(50, 3) * 1.8 - 0.9)
    assert props.sigma_t.shape == (50, 1) and props.albedo.shape == (50, 3) and props.g is None
    if stage == "rte":
        grids = model.property_grids(8)
        t = grids["sigma_a"] + grids["sigma_s"]
        torch.testing.assert_close(t, t[..., :1].expand_as(t))


@pytest.mark.parametrize("sun_threshold,emitters,expect_direct", cases.DIRECT_LIGHT_CASES)
def test_direct_light_only_when_the_scene_has_a_sun_or_emitters(
        tmp_path, monkeypatch, sun_threshold, emitters, expect_direct):
    model, dm = build(tmp_path, f"model.sun.threshold={sun_threshold}",
                      f"scene.effects.emitters={emitters}", "budget.rte.light_warmup=0.01")
    calls = cases.count_calls(monkeypatch, rte_split, "direct_inscatter")
    fit(model, dm, 2)
    assert bool(calls) == expect_direct


def test_medium_waits_for_the_light_field_and_grows_coarse_to_fine(tmp_path, monkeypatch):
    """The photo objective (the medium's only teacher) starts after ``light_warmup`` of the
    run; the modulation grid follows its schedule and its optimizer state restarts at each
    change (:mod:`nrt.modules.fields.coarse_to_fine`)."""
    model, dm = build(tmp_path, "budget.rte.light_warmup=0.5",
                      "budget.rte.medium_resolutions=[2,4]", "budget.rte.medium_upsample_at=[0.5]")
    called = cases.spy_objectives(monkeypatch, model)
    fit(model, dm, 10)
    photo_steps = [s for s, name in called if name == "photo"]
    assert photo_steps and min(photo_steps) == 5
    assert {s for s, name in called if name == "transport"} == set(range(10))
    assert isinstance(model.medium, VoxelMedium) and model.medium.resolution == 4



class RecordRates(L.Callback):
    """The light field's and the medium's learning rates at each training step."""

    def __init__(self):
        self.rates: list[tuple[float, float]] = []

    def on_train_batch_start(self, trainer, pl_module, batch, batch_idx):
        groups = trainer.optimizers[0].param_groups
        medium = next(g for g in groups if g.get("ramps_in"))
        self.rates.append((groups[0]["lr"], medium["lr"]))


@pytest.mark.parametrize("rampup", [0.0, 0.4])
def test_the_medium_rate_ramps_in_after_the_warm_up(tmp_path, rampup):
    """``model.medium_rampup``: the medium's rate (equal to the light field's at the
    config's lr) rises linearly from 0 at the light warm-up's end to the full decayed
    rate over that share of the run; 0 keeps it equal to the light field's throughout."""
    model, dm = build(tmp_path, "budget.rte.light_warmup=0.2", f"model.medium_rampup={rampup}")
    assert model.hparams.lr["light"] == model.hparams.lr["medium"]
    record = RecordRates()
    trainer = fit(model, dm, 10, record)
    assert trainer.global_step == 10
    shares = [medium / light for light, medium in record.rates]
    if rampup == 0:
        assert shares == pytest.approx([1.0] * 10)
        return
    assert shares == sorted(shares) and shares[-1] == pytest.approx(1.0)
    assert shares[0] == 0.0 and sum(0 < s < 1 for s in shares) >= 3, shares


def test_a_medium_rampup_outside_the_run_is_refused(tmp_path):
    with pytest.raises(InstantiationException, match=r"model.medium_rampup=1.5"):
        build(tmp_path, "model.medium_rampup=1.5")

def test_the_extinction_prior_is_the_mean_extinction_and_lowers_it(tmp_path, monkeypatch):
    """``losses.weights.extinction_prior``: its loss is the mean over voxels and channels of
    the medium's extinction; trained after the photo objective (whose backward frees the
    step's voxels, so the prior composes its own) with a weight that dominates the photos',
    it lowers the extinction: from rho = 1 (``init=none``, t = 0) Adam moves each exponent by
    about the learning rate (0.02) per step, so 10 steps take the mean to about
    exp(-0.2) = 0.82, far below 0.95."""
    model, dm = build(tmp_path, "losses.weights.extinction_prior=10.0",
                      "budget.rte.light_warmup=0.01")
    called = cases.spy_objectives(monkeypatch, model)
    fit(model, dm, 10)
    assert {name for _, name in called} == {"photo", "transport", "extinction_prior"}
    voxels = model.medium.voxels()
    mean = voxels.extinction.mean()
    prior = model.objectives["extinction_prior"].loss({}, model.step_context([]))
    torch.testing.assert_close(prior, mean)
    assert float(mean) < 0.95 and torch.isfinite(voxels.stacked).all()


def test_the_total_variation_prior_is_built_by_its_ablation_and_flattens_the_medium(
        tmp_path, monkeypatch):
    """``ablation=extinction_tv`` adds the prior as a unit of the stage; its loss is the
    total variation of the medium's extinction, and with a weight that dominates the
    photos' the medium trained 10 steps (from a flat start, ``init=none``) ends with well
    under the texture the photos give the same run without it, finite everywhere."""
    def trained_tv(*overrides):
        torch.manual_seed(0)
        model, dm = build(tmp_path, "budget.rte.light_warmup=0.01", *overrides)
        called = cases.spy_objectives(monkeypatch, model)
        fit(model, dm, 10)
        voxels = model.medium.voxels()
        assert torch.isfinite(voxels.stacked).all()
        return model, {name for _, name in called}, total_variation(voxels.extinction,
                                                                    voxels.bbox)

    model, names, with_prior = trained_tv("ablation=extinction_tv",
                                          "losses.weights.extinction_tv=10.0")
    assert names == {"photo", "transport", "extinction_prior", "extinction_tv"}
    torch.testing.assert_close(model.objectives["extinction_tv"].loss({}, model.step_context([])),
                               with_prior)
    _, names, without = trained_tv()
    assert "extinction_tv" not in names
    # measured: 0.0071 against 0.0157; a weight of 100 gives 0.0068, the floor Adam's steps
    # of about the learning rate leave as cell-to-cell jitter in 10 steps
    assert float(without) > 0 and float(with_prior) < 0.6 * float(without)


def test_coupling_options_carry_photo_gradients_through_the_scattered_light(tmp_path):
    """``model.coupling``: with the adjoint on, the photo loss's gradient to the coefficient
    grid becomes the adjoint's source and the adjoint grid learns from it (both nonzero
    after the photos start); the unrolled step and the adjoint together train 10 steps
    with finite values everywhere, and the adjoint's state is part of the checkpoint."""
    model, dm = build(tmp_path, "model.coupling.adjoint=true",
                      "model.coupling.unrolled_directions=1", "budget.rte.light_warmup=0.2")
    assert model.adjoint is not None and "adjoint.source" in model.state_dict()
    cases.trains_finite(model, dm, 10)
    assert model.adjoint.source.abs().max() > 0
    assert model.adjoint.grid.coefficients.detach().abs().max() > 0
    assert "adjoint.grid.coefficients" in model.state_dict()


def test_oracle_start_bakes_the_true_extinction(tmp_path):
    """``init=oracle`` (a diagnostic, docs/stage2.md): the medium modulates the dataset's
    true extinction, its channel mean baked on the density's cells, in place of the EA
    density; the paper's formulation refuses it."""
    from nrt.modules.fields.voxel_medium import bake
    from nrt.physics.volume import sample_grid

    model, dm = build(tmp_path, "init=oracle")
    fit(model, dm, 1)
    truth = dm.ground_truth
    extinction = (truth["sigma_a"] + truth["sigma_s"]).float().mean(-1, keepdim=True)
    bbox = model.medium.bbox
    want = bake(lambda x: sample_grid(extinction, x, bbox)[..., 0], 8, bbox)
    torch.testing.assert_close(model.medium.density, want)
    assert want.max() > 0.5  # the tiny scene's medium, not an empty grid
    with pytest.raises(InstantiationException, match="init=oracle") as refused:
        build(tmp_path, "init=oracle", "experiment=rte_paper")
    assert isinstance(refused.value.__cause__, ConfigError)


def test_oracle_start_blends_the_truth_with_the_ea_density(tmp_path):
    """``init=oracle init.truth_share=a``: the start ``EA^(1 - a) truth^a`` on the density's
    cells (each side floored at 1e-4), the EA density read from ``init.ea_ckpt``; a share
    outside [0, 1], or one below 1 without an EA checkpoint, is refused naming the key."""
    from nrt.modules.fields.voxel_medium import bake
    from nrt.physics.volume import sample_grid
    from nrt.stages.ea import load_ea_field
    from tests.conftest import single_scene_ea_checkpoint

    ckpt = single_scene_ea_checkpoint(tmp_path / "ea.ckpt")
    model, dm = build(tmp_path, "init=oracle", f"init.ea_ckpt={ckpt}", "init.truth_share=0.5")
    fit(model, dm, 1)
    truth = dm.ground_truth
    extinction = (truth["sigma_a"] + truth["sigma_s"]).float().mean(-1, keepdim=True)
    bbox = model.medium.bbox
    true_cells = bake(lambda x: sample_grid(extinction, x, bbox)[..., 0], 8, bbox)
    ea_cells = bake(load_ea_field(str(ckpt)).density, 8, bbox)
    want = torch.sqrt(true_cells.clamp_min(1e-4) * ea_cells.clamp_min(1e-4))
    torch.testing.assert_close(model.medium.density, want)
    assert not torch.allclose(want, true_cells) and not torch.allclose(want, ea_cells)
    for bad, key in ((["init.truth_share=1.5"], "init.truth_share=1.5"),
                     (["init.truth_share=0.5"], "init.ea_ckpt")):
        with pytest.raises(InstantiationException, match=key.replace(".", r"\.")) as refused:
            build(tmp_path, "init=oracle", *bad)
        assert isinstance(refused.value.__cause__, ConfigError)


def test_several_environments_train_a_light_field_each(tmp_path):
    """``stage.environments=[0,1]`` on a scene under two skies: the medium is shared and each
    sky has its own light field, scaled by that sky's mean radiance and holding that sky's
    uncollided light; each ray and each held-out view goes through its own sky's light and
    known lights (suns); a checkpoint rebuilds both fields. A stage that learns one
    environment's light (the paper's formulation) refuses two."""
    from nrt.stages.illumination import mean_radiance

    two_skies = ("scene.environments.sky_seeds=[0,1]", "stage.environments=[0,1]")
    model, dm = build(tmp_path, *two_skies, "budget.rte.light_warmup=0.2")
    trainer = fit(model, dm, 10)
    maps = dm.training_environments()
    assert list(maps) == [0, 1] and len(model.env_lights) == len(model.illuminations) == 2
    for light, sky, env in zip(model.env_lights, model.illuminations, maps.values(),
                               strict=True):
        assert model.sky_lights.illumination_of(light) is sky
        assert light.radiance_scale.item() == pytest.approx(mean_radiance(env), rel=1e-6)
        assert light.coefficients.abs().max() > 0  # trained by the transport objective
    first, second = model.env_lights
    assert not torch.allclose(first.uncollided, second.uncollided)  # two different skies
    # the suns differ too: each sky's first scattering comes from its own sun
    assert not torch.allclose(model.illuminations[0].lights.sun_directions,
                              model.illuminations[1].lights.sun_directions)
    assert model.sky_lights.scenes_of(torch.tensor([1, 0, 0, 1])).tolist() == [1, 0, 0, 1]
    view = next(b for b in dm.val_dataloader() if b["env"] == 1)
    torch.manual_seed(0)
    seen = model.predict_view(view)
    torch.manual_seed(0)
    own = model.render_pixels(view["origins"], view["dirs"], view["background"],
                              model.transport_medium(), second)
    torch.testing.assert_close(seen["vre"], own["vre"])
    path = tmp_path / "two_skies.ckpt"
    trainer.save_checkpoint(path)
    loaded = RTEStage.load_from_checkpoint(path)
    assert len(loaded.env_lights) == 2
    torch.testing.assert_close(loaded.more_lights[0].coefficients, second.coefficients)
    paper, paper_dm = build(tmp_path, *two_skies, "experiment=rte_paper")
    with pytest.raises(DatasetError, match="one environment"):
        fit(paper, paper_dm, 1)


@pytest.mark.parametrize("skies", [1, 2])
def test_the_photo_objective_renders_each_twin_with_its_first_ray(tmp_path, monkeypatch,
                                                                  skies):
    """``budget.rte.photo_twins=24`` of 64 photo rays: each step renders the 64 rays and
    then the 24 twins, each twin through its own first ray's sky (under two skies, the
    first rays of each sky's share; a pinhole twin leaves from its first ray's camera), and
    trains with finite values."""
    from nrt.losses import photo

    environments = ([f"scene.environments.sky_seeds={list(range(skies))}",
                     f"stage.environments={list(range(skies))}"] if skies > 1 else [])
    model, dm = build(tmp_path, *environments, "budget.rte.photo_twins=24",
                      "budget.rte.light_warmup=0.01")
    renders: list[tuple[torch.Tensor, torch.Tensor]] = []
    original = photo.render_view_rays

    def spy(medium, origins, dirs, background, *args):
        renders.append((origins, background))
        return original(medium, origins, dirs, background, *args)

    monkeypatch.setattr(photo, "render_view_rays", spy)
    cases.trains_finite(model, dm, 3)
    assert renders and len(renders) % 2 == 0
    firsts, twins = renders[0::2], renders[1::2]
    steps = len(renders) // (2 * skies)
    assert steps >= 1
    assert sum(len(o) for o, _ in firsts) == 64 * steps
    assert sum(len(o) for o, _ in twins) == 24 * steps
    for (first, _), (twin, _) in zip(firsts, twins, strict=True):
        assert 0 < len(twin) <= len(first)
        torch.testing.assert_close(twin, first[:len(twin)], rtol=0, atol=0)


def test_a_sky_whose_share_of_the_batch_holds_no_twin_renders_none(tmp_path, monkeypatch):
    """One twin among 64 photo rays under two skies: only the sky of the batch's first ray
    has a twin, so each step renders three batches (both skies' rays, one twin), none of
    them empty."""
    from nrt.losses import photo

    model, dm = build(tmp_path, "scene.environments.sky_seeds=[0,1]", "stage.environments=[0,1]",
                      "budget.rte.photo_twins=1", "budget.rte.light_warmup=0.01")
    sizes: list[int] = []
    original = photo.render_view_rays

    def spy(medium, origins, *args):
        sizes.append(len(origins))
        return original(medium, origins, *args)

    monkeypatch.setattr(photo, "render_view_rays", spy)
    cases.trains_finite(model, dm, 3)
    assert sizes and len(sizes) % 3 == 0, sizes
    assert min(sizes) > 0, sizes
    assert sum(sizes) == 65 * (len(sizes) // 3), sizes
