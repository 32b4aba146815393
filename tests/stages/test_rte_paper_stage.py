"""The paper's formulation of stage 2 (``experiment=rte_paper``: SIREN light field, RTE
residual, boundary, observation and VRE objectives) end to end: forward mode against
Mitsuba, ``stage=ea`` then ``stage=rte`` via the real CLI, the terms a scene's effects
switch on and off, and hard cases that must never put NaN or Inf anywhere. The default
stage 2 (split) has its own tests in ``test_rte_split_stage.py``."""

import re

import hydra
import numpy as np
import pytest
import torch
from omegaconf import OmegaConf

from nrt.data.render import ensure_dataset
from nrt.stages import radiative_transfer
from tests.conftest import (
    ONE_SKY,
    compose_config,
    last_value,
    only_run_dir,
    read_csv_metrics,
    run_train,
    train_in_process,
    values,
)
from tests.finite_training import fit
from tests.stages import stage2_cases as cases

pytestmark = pytest.mark.e2e

PROPERTIES = ("sigma_a", "sigma_s", "sigma_t", "g")
PAPER = "experiment=rte_paper"


FORWARD_PSNR_MIN = 30.5
"""Held-out PSNR (dB, log tonemap) that forward mode must reach on the tiny scene with
g = 0.7 after its 300 steps. Measured over seeds 0-4: 31.59-32.16 dB (mean
31.88, sd 0.22), so the bound sits ~5 sd below the worst seed. The same runs with the
ground truth's g flipped reach 20.0 dB and with albedo 1 (sigma_a folded into sigma_s)
23.9 dB, 6.6-10.5 dB below the bound; the no-scattering prediction ``T E(v)`` is 22.6 dB.
On the default scene (g = 0.137) a flipped g changes nothing measurable (33.9 dB against
33.4-33.8 over 6 seeds), hence the strongly forward medium here. The seeds ran on a
16-core machine (2 threads each, torch 2.11); seed 0 on these 2 cores gave 31.93 dB, the
same."""


@pytest.mark.slow
def test_forward_mode_reproduces_the_photos(tmp_path, tiny_dataset):
    """Forward mode: the true medium (HG g = 0.7), only the light field learns (RTE + BC,
    no photos). Its VRE image of the held-out views must reproduce Mitsuba's photos to
    :data:`FORWARD_PSNR_MIN` dB, and beat the no-scattering prediction ``T E(v)`` of the
    same medium by > 6 dB (measured 9.0-9.6): only a light field that carries the scattered
    light, with the right lobe and albedo, gets there."""
    proc = run_train(tmp_path, tiny_dataset.parent, "scene.medium.g=0.7", PAPER,
                     "budget.rte.steps=300", stage="forward")
    assert proc.returncode == 0, proc.stderr[-3000:]
    rows = read_csv_metrics(only_run_dir(tmp_path, "forward"))
    ours = last_value(rows, "val/psnr")
    transmitted = last_value(rows, "val/psnr_transmitted_only")
    assert ours > FORWARD_PSNR_MIN and ours > transmitted + 6.0, (ours, transmitted)
    assert "val/mse_sigma_t_x100" not in rows[0]  # the medium is not learned: no such metric


@pytest.mark.slow  # ~30 s for stage 2 after the session's EA run (~30 s)
def test_rte_after_ea_via_cli_fits_the_photos_and_holds_the_medium(tiny_ea_run, tiny_dataset):
    """``stage=ea`` then ``stage=rte experiment=rte_paper`` through the CLI, checked for what
    the paper's formulation does at the tiny budget: it starts from the EA checkpoint and
    says so, logs the time and
    loss of every objective and the property MSEs from step 0, fits the held-out photos
    with its VRE image, and exports the medium in the ground truth's layout.

    It does not improve the medium at this budget: over seeds 0-5 the end/start property
    MSE ratios were sigma_a 0.96-0.99, sigma_s 0.96-1.01, sigma_t 0.97-1.00, g 0.96-1.01,
    so the test bounds drift only (every ratio < 1.10). The held-out VRE PSNR was
    34.35-34.72 dB (the no-scattering prediction ``T E(v)``: 25.4 dB); bound 33.0 dB, ~9 sd
    below the worst seed. Seed 0 on 2 cores (torch 2.14) gives the same as on the 16-core
    machine that measured the seeds: 34.73 dB, sigma_t MSE x100 15.46 -> 15.40."""
    out, ea = tiny_ea_run
    assert ea.returncode == 0, ea.stderr[-3000:]
    ea_ckpt = only_run_dir(out, "ea") / "checkpoints" / "last.ckpt"
    proc = run_train(out / "paper", tiny_dataset.parent, PAPER, f"init.ea_ckpt={ea_ckpt}",
                     "budget.rte.steps=300", stage="rte")
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert f"Stage 2 modulates the EA density of {ea_ckpt}" in proc.stdout + proc.stderr
    run = only_run_dir(out / "paper", "rte")
    rows = read_csv_metrics(run)
    for name in ("rte", "bc", "obs", "vre"):
        assert values(rows, f"time/step_{name}_s") and values(rows, f"train/loss_{name}")
    assert [float(r["step"]) for r in rows if r.get("val/mse_g_x100")][0] == 0
    ratios = {k: last_value(rows, f"val/mse_{k}_x100") / values(rows, f"val/mse_{k}_x100")[0]
              for k in PROPERTIES}
    assert all(r < 1.10 for r in ratios.values()), ratios
    assert last_value(rows, "val/psnr") > 33.0, last_value(rows, "val/psnr")
    with np.load(run / "medium_grids.npz") as grids:
        assert grids["sigma_a"].shape == grids["sigma_s"].shape == (32, 32, 32, 3)
        assert grids["g"].shape == (32, 32, 32)
        assert all(np.isfinite(grids[k]).all() for k in ("sigma_a", "sigma_s", "g"))
    assert list((run / "tensorboard").glob("events.out.tfevents.*"))


@pytest.mark.parametrize(("stage", "overrides", "needle"), [
    ("rte", (), "stage=rte starts from the EA density"),
    ("dpt", (), "stage=dpt starts from the EA density"),
    ("rte", ("init=none", "scene.effects.max_scattering_order=1"), "max_scattering_order=1"),
    ("forward", ("scene.effects.max_scattering_order=0",), "max_scattering_order=0"),
    ("ea", ("budget.ea.steps=-3",), "budget.ea.steps=-3"),
    ("ea", ("budget_s=-5",), "budget_s=-5"),
    ("rte", ("init=none", "budget.rte.photo_twins=-1"), "budget.rte.photo_twins=-1"),
    ("rte", ("init=none", "budget.rte.photo_twins=999"),
     "budget.rte.photo_twins=999: must be at most budget.rte.photo_rays (256)"),
    ("rte", ("init=none", "budget.rte.photo_rays=2048"),
     "budget.rte.photo_rays=2048: must be at most budget.rte.rays_per_batch (256)"),
    ("rte", ("init=none", "budget.rte.vre_rays=2048"),
     "budget.rte.vre_rays=2048: must be at most budget.rte.rays_per_batch (256)"),
    ("ea", ("model.density_field.density_activation=relu",),
     "model.density_field.density_activation"),
    ("rte", ("init=none", "+losses.weights.foo=1"), "losses.weights has unknown objectives"),
    ("rte", ("init=none", "losses.objectives.photo._target_=nrt.losses.photo.photo_loss"),
     "losses.objectives.photo names photo_loss, which is not an objective"),
])
def test_config_refusals_come_before_any_rendering(tmp_path, stage, overrides, needle):
    """What the config alone decides (no EA run to start from; stage 2 on photos of
    truncated transport; counts below 1; unknown names) is refused with ``nrt: error:``
    and exit status 2 before the dataset is rendered or loaded: the data folder (empty
    here, so the scene would have to be rendered first) stays untouched, and the failed
    start leaves no run folder behind. (In the test's process: a refusal costs a
    composition, not a Python start.)"""
    data_root, out = tmp_path / "datasets", tmp_path / "out"
    out.mkdir()
    proc = train_in_process(out, data_root, *overrides, stage=stage)
    assert proc.returncode == 2, proc.stderr[-3000:]
    assert f"nrt: error: {needle}" in proc.stderr or (
        "nrt: error:" in proc.stderr and needle in proc.stderr), proc.stderr[-3000:]
    assert "Traceback" not in proc.stderr
    assert not data_root.exists(), list(data_root.rglob("*"))
    assert list(out.iterdir()) == []


@pytest.mark.parametrize(("overrides", "needle"), [
    (("stage=rte", "init.ea_ckpt=no/such.ckpt"), "init.ea_ckpt='no/such.ckpt'"),
    (("budget.val_every=0",), "budget.val_every=0"),
    (("budget.val_views=-1",), "budget.val_views=-1"),
    (("stage.steps=0",), "stage.steps=0"),
    (("budget.ea.hash_levels=1.5",), "budget.ea.hash_levels=1.5"),
    (("stage=rte", "init=none", "budget.rte.rays_per_batch=0"), "budget.rte.rays_per_batch=0"),
    (("stage=rte", "budget.rte.medium_resolutions=[4,-8]"), "budget.rte.medium_resolutions"),
    (("stage=rte", "budget.rte.light_warmup=1"), "budget.rte.light_warmup=1"),
    (("stage=rte", "init=none", "budget.rte.medium_upsample_at=[0.6,0.4]"), "upsample_at"),
    (("stage=dpt", "init=none", "budget.dpt.upsample_at=[1.5]"), "upsample_at"),
    (("stage=dpt", "init=none", "budget.dpt.extinction_prior=-1"),
     "budget.dpt.extinction_prior=-1"),
    (("losses.photometric=l1",), "losses.photometric"),
    (("model.lr=-0.01",), "model.lr=-0.01"),
    (("stage=rte", "init=none", "model.lr.medium=0"), "model.lr.medium=0"),
    (("stage=rte", "init=none", PAPER, "model.lr.light=-1"), "model.lr.light=-1"),
    (("stage=dpt", "init=none", "losses.lr=0"), "losses.lr=0"),
    (("stage=rte", "init=none", "losses.photo_tonemap=gamma"), "losses.photo_tonemap"),
    (("stage=rte", "init=none", PAPER, "model.medium.modulation=mlp"), "model.medium.modulation"),
    (("stage=rte", "init=none", PAPER, "model.medium.init_albedo=1.5"), "init_albedo"),
    (("stage=rte", "init=none", PAPER, "budget.rte.light_layers=0"), "budget.rte.light_layers"),
    (("stage=rte", "init=none", "scene.effects.phase=rayleigh"), "scene.effects.phase"),
    (("stage=rte", "init=none", "+losses.weights.foo=1"), "unknown objectives ['foo']"),
    (("stage=rte", "init=none", PAPER, "+losses.weights.photo=1"), "unknown objectives ['photo']"),
    (("stage=rte", "init=none", "losses.weights.photo=[1,2]"), "losses.weights.photo=[1, 2]"),
    (("stage=rte", "init=none", PAPER, "ablation=extinction_tv"),
     "losses.objectives.extinction_tv is a prior on a voxel medium"),
])
def test_config_mistakes_are_refused_before_data(overrides, needle):
    """The checks nrt-train makes before it renders or loads data (the budget's counts,
    the EA checkpoint, the model's own) refuse each mistake with an NrtError naming the
    key, which the CLI prints as ``nrt: error:`` with status 2 (the test above)."""
    from hydra.errors import InstantiationException

    from nrt.cli.checks import check_budget, check_objectives
    from nrt.cli.train import resolve_ea_checkpoint
    from nrt.errors import NrtError

    cfg = compose_config("train", ["preset=tiny", *overrides])
    with pytest.raises(NrtError, match=re.escape(needle)):
        try:
            check_budget(cfg)
            check_objectives(cfg)
            resolve_ea_checkpoint(cfg)
            hydra.utils.instantiate(cfg.model, _convert_="all")
        except InstantiationException as exc:  # as nrt.cli.common.run_app unwraps it
            raise exc.__cause__ from None


# ------------------------------------------------------------------ in-process helpers
SMALL = ["budget.rte.collocation_points=256", "budget.rte.boundary_points=256",
         "budget.rte.rays_per_batch=128", "budget.rte.vre_rays=32",
         "budget.rte.vre_samples=12", "budget.rte.inscatter_directions=4"]


def build(tmp_path, *overrides: str, stage: str = "rte", paper: bool = True):
    """Model and DataModule of ``stage=<stage> preset=tiny init=none`` plus ``overrides``
    (with ``paper``: the paper's formulation at small counts), on a 16x16, 8 spp dataset
    under one sky (:data:`tests.conftest.ONE_SKY`) rendered into ``tmp_path``."""
    chosen = [PAPER, *SMALL] if paper else []
    cfg = compose_config("train", [f"stage={stage}", "preset=tiny", "init=none", *ONE_SKY,
                                   *chosen,
                                   "scene.cameras.width=16", "scene.cameras.height=16",
                                   "scene.spp=8", *overrides])
    scene = OmegaConf.to_container(cfg.scene, resolve=True)
    folder = ensure_dataset(scene, tmp_path, progress=False)
    dm = hydra.utils.instantiate(cfg.data, dataset_dir=str(folder))
    model = hydra.utils.instantiate(cfg.model, _convert_="all")
    return model, dm


@pytest.mark.slow
@pytest.mark.parametrize("case", [*cases.HARD_CASES, "sun_1e4"])
def test_hard_cases_train_without_nonfinite_values(tmp_path, case):
    overrides = cases.hard_case_overrides(case, tmp_path)
    model, dm = build(tmp_path, f"scene.name={case}", *overrides)
    cases.trains_finite(model, dm, 100)


@pytest.mark.parametrize("stage", ["rte", "forward"])
def test_stage2_and_forward_mode_run_on_a_grey_scene(tmp_path, stage):
    """``scene=isotropic`` has grey extinction: one sigma_t channel with an RGB albedo (the
    spec draws a coloured albedo and Mitsuba renders it). Stage 2 learns such a medium
    (sigma_t (..., 1), albedo (..., 3), exported grids whose sigma_a + sigma_s is equal in
    R, G and B) and forward mode uses the truth's coloured albedo, not red's for all
    channels; 20 steps of each run with finite values throughout."""
    model, dm = build(tmp_path, "scene=isotropic", stage=stage)
    fit(model, dm, 20)
    pts = torch.rand(500, 3) * 1.8 - 0.9
    props = model.medium(pts)
    assert props.sigma_t.shape == (500, 1) and props.albedo.shape == (500, 3)
    batch = next(iter(dm.val_dataloader()))
    pred = model.predict_pixels(batch["origins"], batch["dirs"], batch["background"])
    assert all(torch.isfinite(p).all() for p in pred.values())
    if stage == "rte":
        grids = model.property_grids(8)
        t = grids["sigma_a"] + grids["sigma_s"]
        torch.testing.assert_close(t, t[..., :1].expand_as(t))
        return
    gt = dm.ground_truth
    sigma_t = gt["sigma_a"] + gt["sigma_s"]
    dense = sigma_t[..., 0] > 0.5  # cell centres inside the medium
    from nrt.physics.volume import cell_centres

    centres = cell_centres(sigma_t.shape[0], model.medium.bbox.cpu())[dense]
    truth_albedo = (gt["sigma_s"] / sigma_t)[dense]
    assert float(np.ptp(truth_albedo.numpy(), -1).mean()) > 0.05  # the truth is coloured
    torch.testing.assert_close(model.medium(centres).albedo, truth_albedo, rtol=1e-4,
                               atol=1e-5)


# ------------------------------------------------------- only what the scene calls for
@pytest.mark.parametrize("sun_threshold,emitters,expect_direct", cases.DIRECT_LIGHT_CASES)
def test_direct_light_only_when_the_scene_has_a_sun_or_emitters(
        tmp_path, monkeypatch, sun_threshold, emitters, expect_direct):
    model, dm = build(tmp_path, f"model.sun.threshold={sun_threshold}",
                      f"scene.effects.emitters={emitters}")
    calls = cases.count_calls(monkeypatch, radiative_transfer, "direct_inscatter")
    fit(model, dm, 2)
    assert bool(calls) == expect_direct


@pytest.mark.parametrize("weights,built", [
    ({"rte": 1.0, "bc": 1.0, "obs": 1.0, "vre": 70.0}, {"rte", "bc", "obs", "vre"}),
    ({"rte": 1.0, "bc": 1.0, "obs": 0.0, "vre": 0.0}, {"rte", "bc"}),
    ({"rte": 0.0, "bc": 0.0, "obs": 1.0, "vre": [0.0, 1.0, 10]}, {"obs"}),
])
def test_only_weighted_objectives_are_built(tmp_path, monkeypatch, weights, built):
    """A zero weight removes an objective entirely (a ramp starting at 0 included)."""
    model, dm = build(tmp_path, "model.sun.threshold=null",
                      *(f"losses.weights.{k}={v}".replace(" ", "") for k, v in weights.items()))
    called = cases.spy_objectives(monkeypatch, model)
    fit(model, dm, 1)
    assert {name for _, name in called} == built


@pytest.mark.slow
def test_furnace_forward_solve_converges_to_the_environment():
    """White furnace in forward mode: sigma_a = 0, random sigma_s, HG g = 0.5, constant
    environment c. The exact solution L = c is constant, so the in-scattering estimate has
    zero variance there and only optimisation limits the fit. From an initial field ~1
    (error > 50% against c = (3, 5, 8)), 600 steps of RTE + BC reach a mean relative error
    of ~0.7% and a 99th percentile of ~2.6% (measured); the bounds leave 2-3x margin."""
    from nrt.losses.boundary import boundary_loss
    from nrt.losses.rte import rte_loss
    from nrt.losses.samplers import boundary_samples, uniform_box_points
    from nrt.modules.fields.light_field import LightField
    from nrt.modules.fields.medium import GroundTruthMedium
    from nrt.physics.phase import sample_uniform_sphere

    torch.manual_seed(0)
    c = torch.tensor([3.0, 5.0, 8.0])
    bbox = torch.tensor([[-1.0] * 3, [1.0] * 3])
    sigma_s = (torch.rand(8, 8, 8, 1) * 4).expand(8, 8, 8, 3)
    medium = GroundTruthMedium({"phase": "hg", "chromatic": True}, torch.zeros(8, 8, 8, 3),
                               sigma_s, torch.full((8, 8, 8), 0.5), bbox)
    light = LightField(hidden=64, layers=3, omega_0=10.0)
    x = uniform_box_points(4096, bbox)
    w = sample_uniform_sphere(torch.rand(4096, 2))

    def relative_error() -> torch.Tensor:
        with torch.no_grad():
            return (light(x, w) / c - 1).abs()

    assert relative_error().mean() > 0.5
    opt = torch.optim.Adam(light.parameters(), lr=1e-3)
    for _ in range(600):
        opt.zero_grad()
        loss = rte_loss(light, medium, uniform_box_points(256, bbox), n_dirs=4)
        pts, dirs = boundary_samples(256, bbox, None, 0.0)
        (loss + boundary_loss(light, pts, dirs, c.expand(256, 3))).backward()
        opt.step()
    err = relative_error()
    assert err.mean() < 0.02 and err.quantile(0.99) < 0.05, (err.mean(), err.quantile(0.99))
