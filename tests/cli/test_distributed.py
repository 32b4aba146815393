"""``nrt-train trainer=ddp_cpu``: a run in two processes on the CPU is one run folder that
rank 0 writes (run.json once, with both ranks' records, checkpoints, exports, the CSV log;
rank 1 adds its log alone), the ranks end in step (the same parameters), ``resume=true``
continues in the same folder and a finished run resumed again is left alone, stage 2
trains from an EA run with its grids doubling, a sweep runs a job in two processes after
another, and the baseline is refused; ``trainer=ddp`` does the same on two GPUs."""

from __future__ import annotations

import json
import os
from pathlib import Path

import pytest
import torch

from nrt.run_dirs import LAST_CKPT, RUN_FILE
from tests.conftest import (
    multirun,
    only_run_dir,
    read_csv_metrics,
    refusal,
    resume_in_place,
    run_train,
    train_in_process,
    values,
)

pytestmark = pytest.mark.e2e

DDP = ("trainer=ddp_cpu", "budget.val_every=10", "budget.checkpoint_every=10")
CORES = len(os.sched_getaffinity(0))


def in_step(run: Path, steps: int) -> dict:
    """``run.json`` of a finished run in two processes: both ranks' records, from two
    processes, at ``steps`` steps with the same parameters (the gradients were averaged)
    on their share of the cores; rank 1 wrote its log."""
    info = json.loads((run / RUN_FILE).read_text())
    ranks = info["ranks"]
    assert info["world_size"] == 2 and [r["rank"] for r in ranks] == [0, 1], info
    assert len({r["pid"] for r in ranks}) == 2
    assert info["finished_step"] == steps and {r["global_step"] for r in ranks} == {steps}
    assert len({r["parameters_sha1"] for r in ranks}) == 1, ranks
    assert {r["threads"] for r in ranks} == {max(1, CORES // 2)}
    logs = sorted(p.name for p in run.glob("*.log"))
    assert len(logs) == 2 and logs[1] == logs[0].replace(".log", "_rank1.log"), logs
    return info


@pytest.mark.gpu
@pytest.mark.slow  # two GPU processes, 30 EA steps
def test_ea_on_two_gpus_is_one_run_in_step(tmp_path, tiny_dataset):
    """``trainer=ddp`` (NCCL, one process per GPU): one run folder that rank 0 writes, the
    ranks in step, each on its own GPU."""
    if torch.cuda.device_count() < 2:
        pytest.skip("needs 2 CUDA devices")
    proc = run_train(tmp_path, tiny_dataset.parent, "trainer=ddp", "trainer.devices=2",
                     *DDP[1:], "budget.ea.steps=30")
    assert proc.returncode == 0, proc.stderr[-3000:]
    info = in_step(only_run_dir(tmp_path, "ea"), 30)
    assert [r["device"] for r in info["ranks"]] == ["cuda:0", "cuda:1"]


@pytest.mark.slow  # three starts of a run in two processes (~45 s)
def test_a_run_in_two_processes_is_one_folder_that_rank_0_writes_and_resumes(tmp_path,
                                                                             tiny_dataset):
    """One run folder, which rank 0 writes: the exports, a checkpoint holding each rank's
    generators, the CSV log, from the session's dataset (found, not rendered again). With
    ``resume=true`` every rank finds the run folder and checkpoint rank 0 resumes; a run
    that finished its steps, resumed again, is left as it is."""
    data = tiny_dataset.parent
    first = run_train(tmp_path, data, *DDP, "budget.ea.steps=20")
    assert first.returncode == 0, first.stderr[-3000:]
    run = only_run_dir(tmp_path, "ea")  # exactly one folder: rank 1 made none
    info = in_step(run, 20)
    assert Path(info["exports"]["density_grid"]).is_file()
    assert info["dataset_dir"] == str(tiny_dataset.resolve())
    saved = torch.load(run / LAST_CKPT, weights_only=False, map_location="cpu")
    assert saved["global_step"] == 20
    assert len(saved["callbacks"]["RandomState"]["ranks"]) == 2  # each rank's generators
    rows = read_csv_metrics(run)
    assert values(rows, "train/loss") and values(rows, "val/psnr")
    saved = resume_in_place(tmp_path, data, run, *DDP, "budget.ea.steps=30")
    assert saved["global_step"] == 30
    in_step(run, 30)
    assert list(run.glob("csv/resumed-*/metrics.csv"))
    kept = {p: p.stat().st_mtime_ns for p in (run / LAST_CKPT, run / RUN_FILE)}
    again = run_train(tmp_path, data, *DDP, "budget.ea.steps=30", "resume=true")
    assert again.returncode == 0, again.stderr[-3000:]
    assert {p: p.stat().st_mtime_ns for p in kept} == kept
    assert "nothing to continue" in again.stdout + again.stderr


@pytest.mark.slow  # the tiny EA run (tiny_ea_run), then 20 stage-2 steps in two processes (~60 s)
def test_stage_2_in_two_processes_from_the_ea_run(tmp_path, tiny_ea_run, tiny_dataset):
    """Stage 2 starts every rank from the EA run that rank 0 resolved, keeps the ranks in
    step through its light warm-up (no medium gradient) and two doublings of its grid,
    and rank 0 alone measures and exports the medium."""
    ea_out, ea = tiny_ea_run
    assert ea.returncode == 0, ea.stderr[-3000:]
    ea_run = only_run_dir(ea_out, "ea")
    (tmp_path / "default" / "ea").mkdir(parents=True)
    (tmp_path / "default" / "ea" / ea_run.name).symlink_to(ea_run)  # the scene's EA run
    proc = run_train(tmp_path, tiny_dataset.parent, *DDP, "budget.rte.steps=20", stage="rte")
    assert proc.returncode == 0, proc.stderr[-3000:]
    run = only_run_dir(tmp_path, "rte")
    info = in_step(run, 20)
    assert info["ea_ckpt"] == str((ea_run / LAST_CKPT).resolve())
    assert Path(info["exports"]["medium_grids"]).is_file()
    rows = read_csv_metrics(run)
    assert values(rows, "train/medium_resolution")[-1] == 16.0  # 4 -> 8 -> 16
    assert values(rows, "train/loss_photo") and values(rows, "val/mse_sigma_t_x100")


@pytest.mark.slow  # a sweep of two jobs, each in two processes (~40 s)
def test_a_sweep_runs_each_job_in_two_processes(tmp_path, tiny_dataset):
    """The jobs of a sweep run one after the other in one process, each starting ranks of
    its own into its own job folder (the ranks run the job, not the sweep)."""
    proc = multirun(tmp_path, tiny_dataset.parent, *DDP, "budget.ea.steps=10", "seed=0,1")
    assert proc.returncode == 0, proc.stderr[-3000:]
    (sweep,) = (tmp_path / "multirun").iterdir()
    jobs = sorted(p for p in sweep.iterdir() if p.is_dir())
    assert [p.name for p in jobs] == ["0", "1"]
    digests = [in_step(job, 10)["ranks"][0]["parameters_sha1"] for job in jobs]
    assert digests[0] != digests[1]  # each job its own seed
    assert not (tmp_path / "default").exists()  # no rank made a run folder of its own


def test_the_baseline_in_two_processes_is_refused(tmp_path):
    """``stage=dpt trainer=ddp_cpu``: one ``nrt: error:`` naming the trainer and the fix,
    status 2, before any data; the run folder is gone (in the test's process)."""
    proc = train_in_process(tmp_path, tmp_path / "datasets", "trainer=ddp_cpu", stage="dpt")
    line = refusal(proc.returncode, proc.stderr)
    assert "stage=dpt" in line and "trainer=ddp_cpu" in line and "trainer=cpu" in line
    assert not list(tmp_path.glob("default/dpt/*"))
    assert not (tmp_path / "datasets").exists()
