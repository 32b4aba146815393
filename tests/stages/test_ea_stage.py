"""Stage 1 (EA) end to end: the real CLI on the tiny preset, kill + resume, and hard
cases (dense and near-empty media) that must never put NaN or Inf in the parameters."""

import math
import time
from pathlib import Path

import numpy as np
import pytest
import torch
from omegaconf import OmegaConf

from nrt.data.datamodule import RayDataModule
from nrt.data.render import ensure_dataset
from nrt.modules.fields.ea_field import EAField
from nrt.run_dirs import SWEEP_FILE, discard_failed_start, new_run_dir, sweep_dir
from nrt.stages.ea import EAModule
from tests.conftest import (
    NRT_TRAIN,
    ONE_SKY,
    cli_in_process,
    compose_config,
    last_value,
    only_run_dir,
    read_csv_metrics,
    train_command,
    train_in_process,
)
from tests.finite_training import fit

pytestmark = pytest.mark.e2e


@pytest.mark.slow
def test_tiny_ea_trains_via_cli_and_beats_background(tiny_ea_run):
    out, proc = tiny_ea_run
    assert proc.returncode == 0, proc.stderr[-3000:]
    run = only_run_dir(out, "ea")
    rows = read_csv_metrics(run)
    psnr, baseline = last_value(rows, "val/psnr"), last_value(rows, "val/psnr_background_only")
    # The background alone explains the sky around the cloud; a learned medium must add
    # a clear margin on held-out views (measured: ~35 dB vs ~26 dB).
    assert psnr > baseline + 5.0, (psnr, baseline)
    assert last_value(rows, "val/density_corr") > 0.7
    assert last_value(rows, "time/wall_s") > 0
    assert (run / "checkpoints" / "last.ckpt").is_file()
    assert (run / "checkpoints" / "best.ckpt").is_file()
    assert list((run / "tensorboard").glob("events.out.tfevents.*"))
    with np.load(run / "density_grid.npz") as grid:
        assert grid["density"].shape == (32, 32, 32) and np.isfinite(grid["density"]).all()


def test_resume_without_checkpoint_is_a_clear_error(tmp_path, tiny_dataset):
    proc = train_in_process(tmp_path, tiny_dataset.parent, "resume=true")
    assert proc.returncode == 2
    assert "nrt: error: resume=True" in proc.stderr and "Traceback" not in proc.stderr
    assert list(tmp_path.iterdir()) == []  # no empty run folder left behind


def test_a_failed_multirun_start_leaves_no_folder(tmp_path):
    """``nrt-train -m``: the first job's start fails (no EA checkpoint), the sweep ends with
    ``nrt: error:`` and status 2, and neither the job's folder nor the sweep's remains."""
    cmd, _ = train_command(tmp_path, tmp_path / "datasets", "seed=0,1",
                           "init.ea_ckpt=no/such.ckpt", stage="rte")
    proc = cli_in_process("train", "-m", *cmd[len(NRT_TRAIN):],
                          env={"NRT_OUTPUT_DIR": str(tmp_path)})
    assert proc.returncode == 2, proc.stderr[-3000:]
    assert "nrt: error: init.ea_ckpt='no/such.ckpt'" in proc.stderr
    assert list(tmp_path.iterdir()) == []


def test_a_failed_sweep_job_removes_its_folder_and_an_empty_sweep(tmp_path):
    """A sweep keeps the folders of the jobs that ran; the sweep's folder goes with its last
    job when only Hydra's multirun.yaml is left (and the folders above it that it made)."""
    sweep = Path(sweep_dir(str(tmp_path / "multirun")))
    for job in ("0", "1"):
        (sweep / job / ".hydra").mkdir(parents=True)
    (sweep / SWEEP_FILE).write_text("hydra: {}")
    (sweep / "0" / "run.json").write_text("{}")  # job 0 ran
    discard_failed_start(sweep / "1", ".hydra", time.time(), sweep)
    assert sorted(p.name for p in sweep.iterdir()) == ["0", SWEEP_FILE]
    alone = Path(sweep_dir(str(tmp_path / "out" / "multirun")))
    (alone / "0" / ".hydra").mkdir(parents=True)
    (alone / SWEEP_FILE).write_text("hydra: {}")
    discard_failed_start(alone / "0", ".hydra", time.time(), alone)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["multirun"]


def test_a_failed_start_removes_only_what_it_wrote(tmp_path):
    """A folder this process named goes (with the folders above it that it created), unless
    it saved a checkpoint; a resumed run keeps everything but this start's config copy."""
    old = tmp_path / "default" / "ea" / "old"
    (old / ".hydra" / "resumed-x").mkdir(parents=True)
    (old / "checkpoints").mkdir()
    (old / "checkpoints" / "last.ckpt").write_text("trained before")
    start = time.time() + 1.0  # this start began after the checkpoint was saved
    discard_failed_start(old, ".hydra/resumed-x", start)
    assert (old / "checkpoints" / "last.ckpt").is_file() and (old / ".hydra").is_dir()
    assert not (old / ".hydra" / "resumed-x").exists()
    fresh = Path(new_run_dir(tmp_path / "default" / "rte" / "new"))
    (fresh / ".hydra").mkdir(parents=True)
    discard_failed_start(fresh, ".hydra/", time.time())
    assert sorted(p.name for p in (tmp_path / "default").iterdir()) == ["ea"]
    (tmp_path / "default" / "dpt").mkdir()  # existed before: kept, though empty
    fresh = Path(new_run_dir(tmp_path / "default" / "dpt" / "new"))
    (fresh / ".hydra").mkdir(parents=True)
    discard_failed_start(fresh, ".hydra/", time.time())
    assert (tmp_path / "default" / "dpt").is_dir() and not (fresh.parent).exists()
    trained = Path(new_run_dir(tmp_path / "default" / "forward"))
    (trained / "checkpoints").mkdir(parents=True)
    (trained / "checkpoints" / "last.ckpt").write_text("saved by this start")
    discard_failed_start(trained, ".hydra/", start - 1.0)
    assert (trained / "checkpoints" / "last.ckpt").is_file()


@pytest.mark.slow
@pytest.mark.parametrize("max_extinction,name", [(50.0, "dense"), (1e-4, "near_empty")])
def test_hard_media_train_without_nonfinite_values(tmp_path, max_extinction, name):
    cfg = compose_config("train", [
        "preset=tiny", *ONE_SKY, f"scene.name={name}",
        f"scene.medium.max_extinction={max_extinction}", "scene.cameras.width=16",
        "scene.cameras.height=16", "scene.spp=8"])
    scene = OmegaConf.to_container(cfg.scene, resolve=True)
    folder = ensure_dataset(scene, tmp_path, progress=False)
    model_cfg = OmegaConf.to_container(cfg.model, resolve=False)
    model_cfg["density_field"]["hash_grid"] = {"levels": 8, "log2_table_size": 15}
    model = EAModule(density_field=model_cfg["density_field"], samples_per_ray=32)
    dm = RayDataModule(str(folder), batch_size=512, steps_per_epoch=200, val_views=1)
    assert fit(model, dm, 200).global_step == 200
    assert torch.isfinite(model.density_grid(16)).all()


def test_ea_colour_reads_the_sh_table_its_weights_were_trained_on():
    """The EA colour net's view input is the real SH table up to degree 2 without the
    Condon-Shortley phase (Sloan's "Stupid SH tricks"; constants from their square roots
    here), the basis trained colour weights are stored in: the
    order and signs are baked into those weights, so a field must give the same
    colour from the same weights. The two bases differ by float32 rounding (~1e-7
    relative), which the MLP passes on at that relative size; 1e-6 leaves room, while the
    Condon-Shortley signs would move colours by far more. Old checkpoints load: the state
    dict gains no key."""
    torch.manual_seed(0)
    field = EAField(hash_grid={"levels": 4, "log2_table_size": 10}, hidden=32)
    for p in field.parameters():  # well away from zero, as after training
        p.data.normal_(0, 0.5)
    x = torch.rand(512, 3) * 2 - 1
    d = torch.nn.functional.normalize(torch.randn(512, 3), dim=-1)
    sigma, rgb = field(x, d)

    a, b = math.sqrt(3 / (4 * math.pi)), math.sqrt(15 / (4 * math.pi))
    c, e = math.sqrt(5 / (16 * math.pi)), math.sqrt(15 / (16 * math.pi))
    dx, dy, dz = d.unbind(-1)
    table = torch.stack((torch.full_like(dx, math.sqrt(1 / (4 * math.pi))), a * dy, a * dz,
                         a * dx, b * dx * dy, b * dy * dz, c * (3 * dz * dz - 1), b * dx * dz,
                         e * (dx * dx - dy * dy)), -1)
    h = field.density_net(field.encode(x))
    expected = torch.nn.functional.softplus(field.color_net(torch.cat((h[..., 1:], table), -1)))
    torch.testing.assert_close(rgb, expected, atol=1e-6, rtol=1e-6)
    flipped = table * torch.tensor([1.0, -1, 1, -1, 1, -1, 1, -1, 1])  # Condon-Shortley
    wrong = torch.nn.functional.softplus(field.color_net(torch.cat((h[..., 1:], flipped), -1)))
    assert (wrong - rgb).abs().max() > 1e-2
    torch.testing.assert_close(sigma, field.density(x))
    assert "sh_signs" not in field.state_dict()
