"""What makes the comparison of stage 2 with the path-tracing baseline fair: both start from
the same medium, both learn g, gradients reach the baseline's parameters through any of its
parametrisations, the property curves are measured outside both methods' clocks, figures
compare only numbers measured the same way, photo-noise realisations are other photos of the
same scene, and tuning never sees a blind scene."""

from __future__ import annotations

import gc
import json
import math
import subprocess
import sys
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
import torch
import yaml
from omegaconf import OmegaConf

from nrt.callbacks import PropertyMetrics, WallClock
from nrt.cameras import Intrinsics
from nrt.cli.checks import check_budget, check_objectives
from nrt.cli.shapes import check_arguments
from nrt.data.spec import resolve_scene, spec_hash
from nrt.errors import SceneError
from nrt.modules.fields.voxel_medium import VoxelMedium
from nrt.physics.volume import cell_centres
from nrt.stages.dpt import DPTModule
from tests.conftest import ROOT, compose_config

pytestmark = pytest.mark.integration

EFFECTS = {"phase": "hg", "chromatic": True, "max_scattering_order": -1, "emitters": []}


def density(x: torch.Tensor) -> torch.Tensor:
    """A smooth blob of extinction up to 4 per unit length, zero far out."""
    return (4.0 * torch.exp(-4.0 * (x ** 2).sum(-1)) - 0.2).clamp_min(0)


@pytest.mark.parametrize(("parametrization", "resolutions"), [
    ("modulated", [4, 8]), ("linear", [8, 16]), ("log", [8, 16])])
def test_the_baseline_starts_from_stage_2s_medium(parametrization, resolutions):
    """Baked on the same 8^3 cells with the same albedo and g = 0, the baseline's first
    medium is stage 2's (VoxelMedium, parametrization=extinction): equal sigma_t, albedo and
    g in every cell (``log`` up to its 1e-3 floor where the density is zero)."""
    stage2 = VoxelMedium(EFFECTS, resolutions=[4, 8], upsample_at=[0.5], density_resolution=8,
                         init_albedo=0.8, parametrization="extinction")
    stage2.set_density(density)
    voxels = stage2.voxels()
    dpt = DPTModule(EFFECTS, {"source": "ea", "ea_ckpt": None}, resolutions, [0.5],
                    parametrization=parametrization, start_resolution=8)
    rho = density(cell_centres(8, torch.tensor([[-1.0] * 3, [1.0] * 3])).reshape(-1, 3))
    dpt.medium.start(rho.reshape(8, 8, 8, 1), torch.full((8, 8, 8, 3), 0.8))
    values = dpt.medium.values()
    floor = 1e-3 if parametrization == "log" else 0.0
    torch.testing.assert_close(values["sigma_t"].detach(),
                               voxels.extinction.expand(-1, -1, -1, 3).clamp_min(floor))
    torch.testing.assert_close(values["albedo"].detach(), voxels.stacked[..., 3:6])
    assert float(values["g"].detach()) == float(voxels.g_shared.detach()) == 0.0
    assert dpt.learns_g  # phase=hg: one g, learned by both


def _one_view(module: DPTModule) -> None:
    c2w = torch.eye(4)
    c2w[2, 3] = 4.0  # on +Z, looking at the box
    frames = SimpleNamespace(intrinsics=Intrinsics.from_fov_x(8, 8, math.radians(40)),
                             root="synthetic", c2w=c2w[None], images=torch.full((1, 8, 8, 3), 0.3),
                             env_index=torch.zeros(1, dtype=torch.long))
    sky = np.full((8, 16, 3), 0.2, np.float32)
    sky[:2] = 5.0
    module.use_views(frames, {0: sky})


def test_gradients_reach_every_parametrisation_by_the_chain_rule():
    """Mitsuba's gradient with respect to the rendered arrays is the same whatever the
    parametrisation (same arrays, same seed); torch carries it on: for ``log`` grids
    (sigma_t = exp(u), albedo = sigmoid(b)) the parameters' gradients are the linear grids'
    times sigma_t and times albedo (1 - albedo)."""
    gc.collect()  # free earlier tests' Mitsuba scenes (a Dr.Jit 3.9 kernel bug, dpt.teardown)
    start = torch.rand(4, 4, 4, 1, generator=torch.Generator().manual_seed(0)) * 3 + 0.5
    albedo = torch.full((4, 4, 4, 3), 0.7)
    grads = {}
    for kind in ("linear", "log"):
        module = DPTModule(EFFECTS, {"source": "ea", "ea_ckpt": None}, [4], [], spp=4,
                           parametrization=kind)
        module.medium.start(start, albedo)
        _one_view(module)
        module.image_loss(0, seed=5)
        grads[kind] = {k: p.grad.clone() for k, p in module.grids().items()}
        module.teardown("test")
    sigma_t = start.expand(-1, -1, -1, 3)
    torch.testing.assert_close(grads["log"]["sigma_t"], grads["linear"]["sigma_t"] * sigma_t,
                               rtol=1e-4, atol=1e-9)
    torch.testing.assert_close(grads["log"]["albedo"],
                               grads["linear"]["albedo"] * albedo * (1 - albedo),
                               rtol=1e-4, atol=1e-9)
    assert grads["linear"]["sigma_t"].abs().max() > 0


def test_the_extinction_prior_adds_its_gradient_to_the_images():
    """``extinction_prior`` w adds w / (number of extinction entries) to every linear
    sigma_t cell's gradient, the images' gradient unchanged (same seed)."""
    gc.collect()
    grads = []
    for weight in (0.0, 0.5):
        module = DPTModule(EFFECTS, {"source": "ea", "ea_ckpt": None}, [4], [], spp=4,
                           extinction_prior=weight)
        module.medium.start(torch.ones(4, 4, 4, 1), torch.full((4, 4, 4, 3), 0.8))
        _one_view(module)
        module.image_loss(0, seed=2)
        grads.append(module.medium.sigma_t.grad.clone())
        module.teardown("test")
    torch.testing.assert_close(grads[1] - grads[0], torch.full_like(grads[0], 0.5 / (64 * 3)),
                               rtol=1e-4, atol=1e-9)


class _Logger:
    def __init__(self):
        self.rows = []

    def log_metrics(self, values, step):
        self.rows.append((step, dict(values)))

    def save(self):
        pass


def test_property_curves_are_measured_every_interval_outside_the_clock(monkeypatch):
    """``every_s``: a measurement each time another interval of training seconds has
    passed, at fixed wall-clock intervals whatever the step rate; the seconds spent
    measuring count in neither the curve's time axis nor the budget."""
    now = [0.0]
    monkeypatch.setattr("nrt.callbacks.time.perf_counter", lambda: now[0])
    clock = WallClock(budget_s=100.0)
    logger = _Logger()
    gt = {"sigma_a": torch.ones(2, 2, 2, 3), "sigma_s": torch.ones(2, 2, 2, 3),
          "g": torch.zeros(2, 2, 2)}

    def measured_grids(resolution):
        now[0] += 7.0  # measuring takes 7 s
        return {k: v.clone() for k, v in gt.items()}

    module = SimpleNamespace(ground_truth=lambda: gt, property_grids=measured_grids,
                             learns_g=True)
    trainer = SimpleNamespace(callbacks=[clock], loggers=[logger], global_step=0,
                              sanity_checking=False, state=SimpleNamespace(fn="fit"))
    metrics = PropertyMetrics(slices=False, every_s=10.0)
    clock.on_train_start(trainer, module)
    for step in range(1, 30):  # a step of 1.5 training seconds each
        now[0] += 1.5
        trainer.global_step = step
        metrics.on_train_batch_end(trainer, module, None, None, step)
    times = [values["time/wall_s"] for _, values in logger.rows]
    assert times == [10.5, 21.0, 30.0, 40.5]  # the first step at or past 10, 20, 30, 40 s
    assert clock.seconds() == pytest.approx(29 * 1.5)  # 4 x 7 s of measuring not counted
    assert all(values["val/mse_sigma_t_x100"] == 0.0 for _, values in logger.rows)
    with pytest.raises(ValueError, match="every_s"):
        PropertyMetrics(every_s=0)


def test_a_photo_seed_is_another_noise_realisation_of_the_same_scene():
    """``scene.photo_seed`` changes the dataset (its hash) and nothing of the scene: the
    medium, skies and cameras are those of seed 0, whose dataset keeps its old name."""
    cfg = compose_config("dataset", ["preset=tiny"])
    scene = OmegaConf.to_container(cfg.scene, resolve=True)
    base = resolve_scene(scene)
    other = resolve_scene({**scene, "photo_seed": 1})
    assert "photo_seed" not in base and other.pop("photo_seed") == 1
    assert other == base  # the same medium, skies, cameras and spp
    assert spec_hash(resolve_scene({**scene, "photo_seed": 1})) != spec_hash(base)
    with pytest.raises(SceneError, match="photo_seed"):
        resolve_scene({**scene, "photo_seed": -1})


def test_figures_of_several_stages_leave_out_each_stages_own_renderer():
    """val/psnr is each stage's own renderer: drawn for runs of one stage, left out when
    stages are compared (eval/psnr_novel, one Mitsuba re-render for all, stays)."""
    from nrt.evaluation.report import RunCurves, drawn_metrics

    one = [RunCurves(Path("a"), "rte", []), RunCurves(Path("b"), "rte", [])]
    mixed = [RunCurves(Path("a"), "rte", []), RunCurves(Path("b"), "dpt", [])]
    assert "val/psnr" in drawn_metrics(one) and "eval/psnr_novel" in drawn_metrics(one)
    assert "val/psnr" not in drawn_metrics(mixed) and "eval/psnr_novel" in drawn_metrics(mixed)


def _record(folder: Path, method: str, times, sigma_t, end_psnr: float,
            provenance: dict | None = None) -> None:
    folder.mkdir(parents=True, exist_ok=True)
    rows = ["wall_s,sigma_a,sigma_s,sigma_t,g"]
    rows += [f"{t},1.0,2.0,{v},0.5" for t, v in zip(times, sigma_t, strict=True)]
    (folder / f"{method}.csv").write_text("\n".join(rows) + "\n")
    metrics = {"mse_sigma_a_x100": 1.0, "mse_sigma_s_x100": 2.0,
               "mse_sigma_t_x100": sigma_t[-1], "mse_g_x100": 0.5, "psnr_novel": end_psnr,
               "ssim_novel": 0.9, "lpips_novel": 0.05, "psnr_noise_floor_novel": 40.0}
    seed, _, variant = folder.name.removeprefix("photo").partition("_")
    (folder / f"{method}.json").write_text(json.dumps({
        "scene": folder.parent.name, "photo_seed": int(seed), "method": method,
        "photo_variant": variant or "auto", "budget_s": 40.0,
        "preset": "tiny", "seconds": times[-1], "steps": 100, "curve_points": len(times),
        "learns_g": True, "metrics": metrics, **(provenance or {})}))


def _provenance(weights: str, gflops: float) -> dict:
    speed = {"gemm_gflops": gflops, "bandwidth_gbs": 10.0}
    return {"code": "abc1234", "ea_ckpt": {"path": "x", "weights_sha256": weights},
            "machine": {"before": speed, "after": speed}}


@pytest.mark.slow  # 6 s: the figure drawn
def test_the_comparison_is_redrawn_from_its_recorded_data_alone(tmp_path):
    """``fair_comparison redraw`` needs only the committed CSV and JSON files: the table
    gives mean and sample sd over realisations (one of them photos of the scalar variant),
    stage 2 against the baseline over the blind scenes and over all, and each method's time
    to reach the other's final sigma_t (never, when it does not)."""
    data = tmp_path / "data"
    times = [0.0, 10.0, 20.0, 30.0, 40.0]
    for k, (photos, shift) in enumerate((("photo0", 0.0), ("photo2_scalar_rgb", 0.2))):
        _record(data / "default" / photos, "rte", times,
                [9.0, 6.0, 4.0 + shift, 3.0 + shift, 2.0 + shift], 35.0 + k)
        _record(data / "default" / photos, "dpt", times,
                [9.0, 8.0, 7.0, 6.5, 6.0], 34.0)
    _record(data / "heldout" / "photo0", "rte", times, [9.0, 5.0, 3.0, 2.5, 2.0], 35.0)
    _record(data / "heldout" / "photo0", "dpt", times, [9.0, 7.0, 5.0, 4.5, 4.0], 34.0)
    _record(data / "heldout2" / "photo0", "rte", times, [9.0, 8.0, 7.0, 6.0, 5.0], 33.0,
            _provenance("aa", 51.0))
    _record(data / "heldout2" / "photo0", "dpt", times, [9.0, 4.0, 3.5, 3.2, 3.0], 34.0,
            _provenance("aa", 49.0))
    _record(data / "heldout2" / "photo1", "rte", times, [9.0, 8.0, 7.0, 6.0, 5.0], 33.0,
            _provenance("aa", 50.0))
    _record(data / "heldout2" / "photo1", "dpt", times, [9.0, 4.0, 3.5, 3.2, 3.0], 34.0,
            _provenance("bb", 50.0))
    figure, table = tmp_path / "fig.png", tmp_path / "table.md"
    proc = subprocess.run([sys.executable, "-m", "benchmarks.fair_comparison", "redraw",
                           "--data", str(data), "--figure", str(figure), "--table", str(table)],
                          cwd=ROOT, capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr[-2000:]
    assert figure.stat().st_size > 10_000
    text = table.read_text()
    assert "| default | stage 2 (nrt) | 2 | 9.000 ± 0.000 | 1.000 ± 0.000 | 2.000 ± 0.000 | " \
        "2.100 ± 0.141 |" in text  # sd of 2.0 and 2.2: 0.2 / sqrt(2)
    assert "| default | path tracing (baseline) | 2 | 9.000 ± 0.000 | 1.000 ± 0.000 | " \
        "2.000 ± 0.000 | 6.000 ± 0.000 |" in text
    assert "35.500 ± 0.707" in text  # the PSNR over the two realisations
    # stage 2 reaches the baseline's end (6.0) at 10 s; the baseline never reaches 2.0 / 2.2
    assert "| default | photo0 | 10 | never (> 40) | 40 |" in text
    assert "| default | photo2_scalar_rgb | 10 | never (> 40) | 40 |" in text
    # stage 2 never reaches the baseline's end on heldout2; the baseline reaches its at 10 s
    assert "| heldout2 | photo0 | never (> 40) | 10 | 40 |" in text
    # over scenes: per-scene ratios of the realisations' means: sigma_t 2.1 / 6, 2 / 4, 5 / 3
    blind = next(line for line in text.splitlines() if line.startswith("| blind |"))
    every = next(line for line in text.splitlines() if line.startswith("| all |"))
    assert "| 0.91x (0.50-1.67), 1/2 |" in blind and "+0.00 dB (-1.00 to +1.00), 1/2" in blind
    assert "| 0.66x (0.35-1.67), 2/3 |" in every, every
    assert "+0.50 dB (-1.00 to +1.50), 2/3" in every, every
    assert "| 1.00x (1.00-1.00), 0/3 |" in every  # equal errors: not better
    # provenance: the commits, whether both started from one EA's weights, the machine's speed
    assert "| heldout2 | photo0 | abc1234 | yes | dpt 49, rte 51 |" in text
    assert "| heldout2 | photo1 | abc1234 | NO | dpt 50, rte 50 |" in text
    assert "| heldout | photo0 | not recorded | not recorded | not recorded |" in text


def test_a_comparison_folder_holds_one_set_of_shared_overrides(tmp_path):
    """Records made with other ``--given-to-all`` overrides are never mixed into a run: it
    stops with exit status 2, naming the record, before any training."""
    data = tmp_path / "data"
    _record(data / "default" / "photo0", "rte", [0.0, 40.0], [9.0, 5.0], 35.0)
    proc = subprocess.run([sys.executable, "-m", "benchmarks.fair_comparison", "run",
                           "--scenes", "default", "--photo-seeds", "0", "--methods", "rte",
                           "--given-to-all", "budget.rte.medium_resolutions=[4,8,16,32,64]",
                           "--data", str(data), "--out", str(tmp_path / "out")],
                          cwd=ROOT, capture_output=True, text=True, timeout=120)
    assert proc.returncode == 2, proc.stderr[-2000:]
    assert str(data / "default" / "photo0" / "rte.json") in proc.stderr
    assert "--given-to-all none" in proc.stderr and not (tmp_path / "out").exists()


def test_a_realisation_of_the_scalar_variant_is_a_scene_of_its_own():
    """Photos of another variant never share a name (and so a dataset folder or EA run)
    with the same seed's photos of the best variant."""
    from benchmarks.fair_comparison import realisation_folder, scene_overrides

    assert scene_overrides("heldout", 0) == ("heldout", ["scene=heldout"])
    name, overrides = scene_overrides("heldout", 0, "scalar_rgb")
    assert name == "heldout_photo0_scalar_rgb" and "render.variant=scalar_rgb" in overrides
    assert f"scene.name={name}" in overrides and "scene.photo_seed=0" in overrides
    assert realisation_folder(1) == "photo1"
    assert realisation_folder(0, "scalar_rgb") == "photo0_scalar_rgb"


def test_tuning_refuses_a_blind_scene(tmp_path):
    """No default may be chosen on a blind scene: the tuning sweep refuses one (exit 2)
    before anything is trained."""
    proc = subprocess.run([sys.executable, "-m", "benchmarks.baseline_tuning", "--scenes",
                           "default,heldout2", "--table", str(tmp_path / "t.csv"),
                           "--out", str(tmp_path)], cwd=ROOT, capture_output=True, text=True,
                          timeout=120)
    assert proc.returncode == 2
    assert "heldout2" in proc.stderr and "tuning scenes" in proc.stderr
    assert not (tmp_path / "t.csv").exists()


@pytest.mark.slow  # ~10 s: one composition per distinct configuration
@pytest.mark.parametrize("stage", ["dpt", "rte"])
def test_every_tuning_configuration_composes(stage):
    """Each configuration of each round of the stage's tuning file is a list of overrides
    that composes with the stage at the cpu preset, passes the config checks and sets
    each overridden key to its value; a hybrid's two parts (stage 2's overrides, then the
    baseline's) each do so with their own stage."""
    from benchmarks.baseline_tuning import CONFIGS

    rounds = yaml.safe_load(CONFIGS[stage].read_text())
    assert rounds and all(isinstance(configs, dict) and configs for configs in rounds.values())
    distinct: dict[tuple, str] = {}
    for configs in rounds.values():
        for name, config in configs.items():
            if isinstance(config, dict):  # a hybrid: stage 2, then the baseline
                distinct[("rte", *config.get("overrides", []))] = name
                distinct[("dpt", *config.get("dpt_overrides", []))] = name
            else:
                distinct[(stage, *config)] = name
    for (part, *overrides), name in distinct.items():
        cfg = compose_config("train", [f"stage={part}", "preset=cpu", *overrides])
        check_budget(cfg)
        check_objectives(cfg)
        check_arguments(cfg)
        for override in overrides:
            key, value = override.split("=", 1)
            actual = OmegaConf.select(cfg, key)
            if OmegaConf.is_config(actual):
                actual = OmegaConf.to_container(actual, resolve=True)
            assert actual == yaml.safe_load(value), (name, key)


def test_several_views_a_step_average_their_gradients():
    """``views_per_step``: the gradient of a step over views [0, 0] (Mitsuba seeds s, s + 1)
    is the mean of the one-view gradients at those seeds, and so is the returned loss."""
    gc.collect()
    start = torch.rand(4, 4, 4, 1, generator=torch.Generator().manual_seed(1)) * 3 + 0.5
    module = DPTModule(EFFECTS, {"source": "ea", "ea_ckpt": None}, [4], [], spp=4)
    module.medium.start(start, torch.full((4, 4, 4, 3), 0.7))
    _one_view(module)
    single = []
    for seed in (7, 8):
        loss = module.image_loss(0, seed=seed)
        single.append((loss, {k: p.grad.clone() for k, p in module.grids().items()}))
    loss = module.image_loss([0, 0], seed=7)
    assert loss == pytest.approx((single[0][0] + single[1][0]) / 2, rel=1e-5)
    for name, p in module.grids().items():
        torch.testing.assert_close(p.grad, (single[0][1][name] + single[1][1][name]) / 2,
                                   rtol=1e-4, atol=1e-9)
    module.teardown("test")


def test_the_rate_decays_and_drops_at_its_fractions():
    """The rate is ``lr * lr_final_factor ** progress * lr_drop_factor ** (drops passed)``:
    the exponential decay of stage 2 and the step drops of the differential-ratio-tracking
    code, composable."""
    module = DPTModule(EFFECTS, {"source": "ea", "ea_ckpt": None}, [4], [], lr=0.02,
                       lr_final_factor=0.1, lr_drops=[0.5, 0.75], lr_drop_factor=0.5)
    (opt,), (sched,) = module.configure_optimizers()
    rate = sched["scheduler"].lr_lambdas[0]
    for progress, want in ((0.0, 1.0), (0.4, 0.1 ** 0.4), (0.5, 0.1 ** 0.5 * 0.5),
                           (0.8, 0.1 ** 0.8 * 0.25), (1.0, 0.1 * 0.25)):
        module.progress = lambda p=progress: p
        assert rate(0) == pytest.approx(want), progress


def test_g_learns_at_its_own_factor_of_the_rate():
    """``lr_g_factor`` scales g's rate only; the grids keep ``lr`` and both follow one
    schedule. Without a learned g there is one group."""
    module = DPTModule(EFFECTS, {"source": "ea", "ea_ckpt": None}, [4], [], lr=0.02,
                       lr_g_factor=0.1)
    (opt,), _ = module.configure_optimizers()
    rates = {id(p): group["lr"] for group in opt.param_groups for p in group["params"]}
    grids = module.grids()
    assert rates[id(grids.pop("g"))] == pytest.approx(0.002)
    assert {rates[id(p)] for p in grids.values()} == {0.02}
    assert len(rates) == len(list(module.parameters()))
    fixed = DPTModule(EFFECTS, {"source": "ea", "ea_ckpt": None}, [4], [], phase_g=0.3)
    (opt,), _ = fixed.configure_optimizers()
    assert len(opt.param_groups) == 1
