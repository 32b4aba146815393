"""nrt-eval, nrt-report, the metric callbacks and budget_s, through the real CLIs.

The must-show of the evaluation: the dataset's own grids score property MSE 0 and a
re-render PSNR within Monte Carlo noise of the noise floor; a wrong medium scores clearly
worse. LPIPS runs with the real weights of nrt-weights (tests/test_weights.py checks their
values) and skips only when they are absent; nrt-eval checks its inputs before loading it.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from types import SimpleNamespace

import numpy as np
import pytest
import torch

from nrt.callbacks import WallClock
from nrt.data.grids import load_property_grids, save_property_grids
from nrt.errors import NrtError
from nrt.evaluation.evaluate import (
    choose_environments,
    named_environments,
    seen_environments,
)
from nrt.metrics import ssim
from nrt.weights import LPIPS_FILES, weights_dir
from tests.conftest import (
    cli_in_process,
    eval_metrics,
    read_csv_metrics,
    run_eval,
    run_train,
    values,
)

pytestmark = pytest.mark.e2e

NRT_REPORT = [sys.executable, "-m", "nrt.cli.report"]


LPIPS_WEIGHTS = (weights_dir() / LPIPS_FILES["alex"]).is_file()
"""The LPIPS weights are installed (``nrt-weights``; CI installs them)."""


@pytest.fixture(scope="module")
def truth_eval(tmp_path_factory, tiny_dataset):
    """nrt-eval of the dataset's own ground truth (grids mode); LPIPS with the real weights
    where they are installed."""
    out = tmp_path_factory.mktemp("eval_truth")
    proc = run_eval(out, tiny_dataset.parent, f"grids={tiny_dataset / 'ground_truth.npz'}",
                    f"metrics.lpips={str(LPIPS_WEIGHTS).lower()}")
    return eval_metrics(proc, out)


def test_ground_truth_scores_zero_mse_and_the_noise_floor(truth_eval):
    metrics, folder = truth_eval
    for key in ("sigma_a", "sigma_s", "sigma_t", "g"):
        assert metrics[f"mse_{key}_x100"] == 0.0
    # Both renders are independent Monte Carlo estimates at the dataset's spp, compared
    # with the same photos: their PSNRs differ by noise only. Per frame they spread by
    # ~1 dB (4 frames of 32x32 here), so the 4-frame means agree to well within 1.5 dB.
    # The tiny scene trains on sky0 and sky1 (scene.environments.train): by default a grid
    # file's held-out views are re-rendered under the novel sky2 only.
    assert not [k for k in metrics if "seen" in k], sorted(metrics)
    assert abs(metrics["psnr_novel"] - metrics["psnr_noise_floor_novel"]) < 1.5
    assert metrics["psnr_env_sky2"] == metrics["psnr_novel"]
    assert metrics["psnr_novel"] > 25 and metrics["ssim_novel"] > 0.9
    assert (folder / "metrics.md").read_text().count("| mse_") == 4
    assert len(list((folder / "previews").glob("*.png"))) == 4
    assert list((folder / "relight").glob("ours_view*.exr"))
    assert list((folder / "relight").glob("relit_view*.png"))
    assert list((folder / "tensorboard").glob("events.out.tfevents*"))
    assert {p.name for p in (folder / "volumes").iterdir()} == {
        "sigma_t.vol", "albedo.vol", "medium.xml"}  # default scene: one HG g, no g grid


def test_eval_draws_its_report_figure_into_the_folder_and_tensorboard(truth_eval):
    """report.png (nrt.evaluation.report_figure; its content:
    tests/evaluation/test_report_figure.py) of the truth against itself, the novel sky's views
    at least 256 px; the same image in TensorBoard."""
    from PIL import Image
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    metrics, folder = truth_eval
    image = np.asarray(Image.open(folder / "report.png").convert("RGB"))
    # the slice rows (>= 128 px each; three at the least) and 3 views of >= 256 px
    assert image.shape[0] > 3 * 128 + 3 * 256 and image.shape[1] > 3 * 256
    acc = EventAccumulator(str(folder / "tensorboard"), size_guidance={"images": 0})
    acc.Reload()
    (event,) = acc.Images("eval/report")
    assert (event.height, event.width) == image.shape[:2]


@pytest.mark.slow
def test_a_wrong_medium_scores_clearly_worse(truth_eval, tiny_dataset, tmp_path):
    truth, _ = truth_eval
    gt = load_property_grids(tiny_dataset / "ground_truth.npz")
    wrong = {"sigma_a": gt["sigma_a"] * 2, "sigma_s": gt["sigma_s"] * 0.5, "g": gt["g"]}
    save_property_grids(tmp_path / "wrong.npz", wrong, gt["bbox"])
    proc = run_eval(tmp_path, tiny_dataset.parent, f"grids={tmp_path / 'wrong.npz'}",
                    "metrics.lpips=false", "rerender.noise_floor=false", "relight.enabled=false",
                    "export.mitsuba=false")
    metrics, _ = eval_metrics(proc, tmp_path)
    assert metrics["mse_sigma_a_x100"] > 0.1 and metrics["mse_sigma_s_x100"] > 1.0
    assert metrics["psnr_novel"] < truth["psnr_noise_floor_novel"] - 3.0
    assert metrics["ssim_novel"] < truth["ssim_novel"]


@pytest.mark.skipif(not LPIPS_WEIGHTS, reason="LPIPS weights absent: run nrt-weights (CI does)")
def test_eval_reports_real_lpips(truth_eval):
    metrics, _ = truth_eval
    # the true medium re-rendered: Monte Carlo noise only (32x32 views at the tiny spp)
    assert 0.0 < metrics["lpips_novel"] < 0.2


def test_lpips_missing_weights_is_a_clear_cli_error(tmp_path, tiny_dataset):
    proc = cli_in_process("eval", "preset=tiny", f"paths.data_dir={tiny_dataset.parent}",
                          "render.progress=false", f"grids={tiny_dataset / 'ground_truth.npz'}",
                          env={"NRT_OUTPUT_DIR": str(tmp_path),
                               "NRT_WEIGHTS_DIR": str(tmp_path / "empty")})
    assert proc.returncode == 2
    assert "nrt-weights" in proc.stderr and "metrics.lpips=false" in proc.stderr
    assert "Traceback" not in proc.stderr


@pytest.mark.parametrize(("overrides", "needle"), [
    ((), "needs run=<run folder"),
    (("run={tmp}/missing/run",), "does not exist"),
    (("run={tmp}",), "is not a run folder of nrt-train"),
    (("grids={tmp}/missing.npz",), "is not a file"),
    (("grids={data}/ground_truth.npz", "scene.effects.phase=nope"), "effects.phase"),
])
def test_eval_input_errors_come_before_metric_setup(tmp_path, tiny_dataset, overrides, needle):
    """Reported as what they are even when the LPIPS weights are missing (in the test's
    process: a refusal costs a composition, not a Python start)."""
    overrides = [o.format(tmp=tmp_path, data=tiny_dataset) for o in overrides]
    proc = cli_in_process("eval", "preset=tiny", f"paths.data_dir={tiny_dataset.parent}",
                          "render.progress=false", *overrides,
                          env={"NRT_OUTPUT_DIR": str(tmp_path / "out"),
                               "NRT_WEIGHTS_DIR": str(tmp_path / "empty")})
    assert proc.returncode == 2 and needle in proc.stderr, proc.stderr[-2000:]
    assert "nrt-weights" not in proc.stderr
    assert not (tmp_path / "missing").exists()  # no eval folder inside a missing run


def test_ssim_is_one_for_equal_images_and_falls_with_noise():
    img = torch.rand(32, 32, 3) * 5
    noisy = img * (1 + 0.3 * torch.randn_like(img)).clamp_min(0)
    assert float(ssim(img, img)) == pytest.approx(1.0, abs=1e-5)
    assert float(ssim(noisy, img)) < 0.95


def test_seen_environments_are_the_trained_ones_or_else_the_first():
    """A run's training environments are its seen ones; for a grid file nrt-eval names the
    scene's training skies (``scene.environments.train``); with none known the first
    environment (every stage trains on it) counts as seen: with a single environment,
    nothing is labelled novel."""
    three = SimpleNamespace(env_names=["sky0", "sky1", "sky2"], root="d")
    assert seen_environments(three, ["sky1"]) == ["sky1"]
    assert seen_environments(three, []) == ["sky0"]
    assert choose_environments(three, "novel", seen_environments(three, [])) == ["sky1", "sky2"]
    one = SimpleNamespace(env_names=["sky0"], root="d")
    assert seen_environments(one, []) == ["sky0"]
    # nrt-eval grids=<file>: the scene's training skies (scene.environments.train) stand in
    assert named_environments(three, [0, 1]) == ["sky0", "sky1"]
    assert named_environments(three, ["sky2", 5]) == ["sky2"]
    assert named_environments(three, None) == ["sky0", "sky1", "sky2"]


def test_novel_environments_are_those_not_trained_on():
    data = SimpleNamespace(env_names=["sky0", "sky1", "sky2"], root="d")
    assert choose_environments(data, "novel", ["sky0"]) == ["sky1", "sky2"]
    assert choose_environments(data, "novel", ["sky0", "sky1", "sky2"]) == ["sky0", "sky1",
                                                                             "sky2"]
    assert choose_environments(data, [1, "sky2"], ["sky0"]) == ["sky1", "sky2"]
    with pytest.raises(NrtError, match="sky9"):
        choose_environments(data, ["sky9"], [])


@pytest.mark.parametrize("resolution", [5, 12])
def test_property_grids_resample_as_a_lookup_at_the_new_cell_centres(resolution):
    """nrt-eval scores a medium on the ground truth's cells through ``resample_grids``,
    which resamples with :func:`~nrt.physics.volume.resample_cells` (the one resampler).
    Reference: the trilinear lookup :func:`sample_grid` (``grid_sample``) at the new cells'
    centres in a box that is not the unit box (the box must not matter). Both are float32
    trilinear weights of the same 8 cells, differing in rounding only: a few ulps of values
    of order 1, so 1e-5 is far below any misplaced cell (which moves values by ~0.1 here).
    A grid already at the resolution comes back unchanged."""
    from nrt.data.grids import resample_grids
    from nrt.physics.volume import cell_centres, sample_grid

    gen = torch.Generator().manual_seed(0)
    grids = {"sigma_a": torch.rand(8, 8, 8, 3, generator=gen),
             "sigma_s": torch.rand(8, 8, 8, 3, generator=gen) * 4,
             "g": torch.rand(8, 8, 8, generator=gen) * 1.8 - 0.9}
    box = torch.tensor([[-1.5, 0.0, 2.0], [0.5, 3.0, 2.5]])
    out = resample_grids(grids, resolution)
    stacked = torch.cat((grids["sigma_a"], grids["sigma_s"], grids["g"][..., None]), -1)
    expected = sample_grid(stacked, cell_centres(resolution, box), box)
    assert out["g"].shape == (resolution,) * 3 and out["sigma_s"].shape == (resolution,) * 3 + (3,)
    for key, sl in (("sigma_a", slice(0, 3)), ("sigma_s", slice(3, 6)), ("g", 6)):
        torch.testing.assert_close(out[key], expected[..., sl], atol=1e-5, rtol=1e-5)
    same = resample_grids(grids, 8)
    assert all(same[k] is grids[k] for k in grids)


def test_mitsuba_export_renders_like_the_dataset_scene(tmp_path, tiny_dataset):
    """medium.xml + .vol files describe the same medium as the renderer's scene dict."""
    from nrt.mitsuba.export import write_medium_files
    from nrt.mitsuba.scene import scene_dict
    from nrt.mitsuba.variant import select_variant

    mi = select_variant("auto")
    spec = json.loads((tiny_dataset / "scene.json").read_text())["spec"]
    gt = load_property_grids(tiny_dataset / "ground_truth.npz")
    grids = {k: gt[k].numpy() for k in ("sigma_a", "sigma_s", "g")}
    files = write_medium_files(mi, tmp_path, grids, spec["bbox"],
                                               spec["effects"])
    sky = np.full((8, 16, 3), 0.5, np.float32)
    scene_ref = mi.load_dict(scene_dict(mi, spec, grids, sky, 16, 16, 40.0, 16))
    scene_exp = mi.load_file(files["xml"])
    p_ref, p_exp = mi.traverse(scene_ref), mi.traverse(scene_exp)
    for key in ("sigma_t.data", "albedo.data"):
        ref = np.array(p_ref[next(k for k in p_ref.keys() if k.endswith(key))])
        exp = np.array(p_exp[next(k for k in p_exp.keys() if k.endswith(key))])
        np.testing.assert_array_equal(ref, exp)
    assert scene_ref.shapes()[0].bbox() == scene_exp.shapes()[0].bbox()


@pytest.fixture(scope="module")
def tiny_sweep(tmp_path_factory, tiny_ea_run, tiny_dataset):
    """The accuracy_vs_time experiment, shrunk: two settings of a few steps each."""
    out, ea = tiny_ea_run
    assert ea.returncode == 0, ea.stderr[-2000:]
    proc = run_train(out, tiny_dataset.parent, "experiment=accuracy_vs_time",
                     "ablation=base,linear_photos", "budget.rte.steps=12", "budget.val_every=6",
                     "budget.checkpoint_every=6", stage="rte")
    assert proc.returncode == 0, proc.stderr[-3000:]
    sweeps = sorted((out / "multirun").iterdir())
    return out, sweeps[-1]


@pytest.mark.slow
def test_report_draws_one_curve_per_sweep_setting(tiny_sweep, tmp_path):
    _, sweep = tiny_sweep
    proc = subprocess.run([*NRT_REPORT, str(sweep), "--out", str(tmp_path)],
                          capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr[-2000:]
    assert (tmp_path / "accuracy_vs_time.png").stat().st_size > 10_000
    rows = (tmp_path / "accuracy_vs_time.csv").read_text().splitlines()[1:]
    labels = {r.split(",")[0] for r in rows}
    assert labels == {"ablation=base", "ablation=linear_photos"}
    psnr_times = [float(r.split(",")[4]) for r in rows
                  if r.startswith("ablation=base,") and ",val/psnr," in r]
    assert len(psnr_times) == 2 and psnr_times[0] < psnr_times[1]
    mse = [r for r in rows if r.startswith("ablation=base,") and "mse_sigma_t" in r]
    assert float(mse[0].split(",")[4]) < 0.05  # the step-0 point of the curve
    assert "ablation=linear_photos" in (tmp_path / "summary.md").read_text()
    assert "Best accuracy/time frontier" in proc.stdout


@pytest.mark.slow
def test_eval_of_a_trained_run_and_export_at_a_chosen_resolution(tiny_sweep, tiny_dataset):
    out, sweep = tiny_sweep
    run = sweep / "0"
    assert (run / "medium_grids.npz").is_file()
    proc = run_eval(out, tiny_dataset.parent, f"run={run}", "metrics.lpips=false",
                    "export.resolution=16", "relight.enabled=false",
                    "rerender.noise_floor=false")
    metrics, folder = eval_metrics(proc, run)
    assert folder.parent == run / "eval"
    grids = load_property_grids(folder / "medium_grids.npz")
    assert grids["sigma_a"].shape == (16, 16, 16, 3)
    info = json.loads((run / "run.json").read_text())
    assert info["stage"] == "rte" and info["environments"] == ["sky0", "sky1"]
    # by default re-rendered under the sky the run did not train on only
    assert "psnr_novel" in metrics and "psnr_seen" not in metrics
    assert np.isfinite(metrics["mse_sigma_t_x100"])


@pytest.mark.slow
def test_budget_s_stops_training_on_training_seconds(tiny_ea_run, tiny_dataset, tmp_path):
    ea_ckpt = next((tiny_ea_run[0] / "default" / "ea").glob("*/checkpoints/last.ckpt"))
    proc = run_train(tmp_path, tiny_dataset.parent, "budget_s=4", "budget.rte.steps=100000",
                     "budget.val_every=5", f"init.ea_ckpt={os.path.relpath(ea_ckpt)}",
                     stage="rte")  # a relative init.ea_ckpt is recorded as an absolute path
    assert proc.returncode == 0, proc.stderr[-2000:]
    run = next((tmp_path / "default" / "rte").iterdir())
    assert json.loads((run / "run.json").read_text())["ea_ckpt"] == str(ea_ckpt.resolve())
    assert f"ea_ckpt: {ea_ckpt.resolve()}" in (run / ".hydra" / "config.yaml").read_text()
    rows = read_csv_metrics(run)
    wall, steps = values(rows, "time/wall_s"), values(rows, "step")
    assert 4.0 <= max(wall) < 30.0 and max(steps) < 100000
    assert "Time budget of 4 s spent" in proc.stdout + proc.stderr


def test_wall_clock_pauses_during_validation(monkeypatch):
    now = [0.0]
    monkeypatch.setattr("nrt.callbacks.time.perf_counter", lambda: now[0])
    clock = WallClock()
    fit = SimpleNamespace(sanity_checking=False, state=SimpleNamespace(fn="fit"))
    clock.on_train_start(fit, None)
    now[0] = 10.0
    clock.on_validation_start(fit, None)
    now[0] = 25.0  # validation: not counted
    assert clock.seconds() == 10.0
    clock.on_validation_end(fit, None)
    now[0] = 30.0
    assert clock.seconds() == 15.0
    with pytest.raises(ValueError, match="budget_s"):
        WallClock(budget_s=0)
