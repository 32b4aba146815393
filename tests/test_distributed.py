"""The rank rules of nrt/distributed.py, one by one: seeds and ray streams per rank, which
metrics are means over the ranks, how many processes a trainer config trains in, the
threads of a job, the command that starts a rank, and the generators and clock that the
ranks keep apart or share."""

from __future__ import annotations

import random
import sys
from pathlib import Path
from types import SimpleNamespace

import pytest
import torch
from hydra import compose, initialize_config_dir
from hydra.core.hydra_config import HydraConfig
from hydra.core.override_parser.overrides_parser import OverridesParser
from omegaconf import open_dict

from nrt.callbacks import RandomState, WallClock
from nrt.cameras import Intrinsics
from nrt.cli.checks import SEEDS, processes
from nrt.cli.common import CONFIG_DIR, register_resolvers
from nrt.data.datamodule import RandomRays, RayDataModule
from nrt.data.dataset import SceneDataset
from nrt.distributed import (
    child_command,
    job_threads,
    process_count,
    rank_seed,
    synced,
)
from nrt.physics.envmap import EnvironmentMap
from nrt.stages.schedules import training_progress
from tests.conftest import compose_config

pytestmark = pytest.mark.unit


def test_rank_0_keeps_the_seed_and_every_rank_draws_its_own_numbers():
    """Rank 0 keeps the run's seed; the others get seeds that torch's CPU generator tells
    apart (it keeps 32 bits), of no other rank of the first seeds and no neighbouring run."""
    assert rank_seed(7, 0) == 7 and rank_seed(7, 1) == rank_seed(7, 1)
    seeds = [rank_seed(s, r) for s in (*range(64), SEEDS - 1) for r in range(4)]
    assert all(0 <= s < SEEDS for s in seeds)
    assert len(set(seeds)) == len(seeds)  # no two (seed, rank) share a stream
    first = {torch.rand(1, generator=torch.Generator().manual_seed(rank_seed(7, r))).item()
             for r in range(4)}
    assert len(first) == 4


def views() -> SceneDataset:
    """Two 8 x 8 photos from cameras outside the unit box, under one constant sky."""
    c2w = torch.eye(4).repeat(2, 1, 1)
    c2w[:, 2, 3] = 4.0
    c2w[1, 0, 3] = 0.5
    return SceneDataset(root=Path("views"), split="train",
                        images=torch.rand(2, 8, 8, 3, generator=torch.Generator().manual_seed(0)),
                        c2w=c2w, intrinsics=Intrinsics.from_fov_x(8, 8, 0.7),
                        env_index=torch.zeros(2, dtype=torch.long), env_names=["sky"],
                        envmaps=[EnvironmentMap(torch.ones(3, 4, 3))],
                        bbox=torch.tensor([[-1.0] * 3, [1.0] * 3]), ground_truth=None,
                        spec=None)


def first_batch(rank: int, seed: int = 3) -> dict:
    """The first training batch the data module gives rank ``rank`` of a run of ``seed``."""
    data = RayDataModule("views", batch_size=64, steps_per_epoch=2, seed=seed)
    data.train_data = views()
    data.trainer = SimpleNamespace(global_rank=rank, global_step=0)
    return next(iter(data.train_dataloader()))


def test_each_rank_draws_its_own_rays_and_rank_0_those_of_one_process():
    alone = next(iter(RandomRays(views(), 64, 2, seed=3)))
    ranks = [first_batch(rank) for rank in range(3)]
    for key, value in alone.items():
        torch.testing.assert_close(ranks[0][key], value, rtol=0, atol=0)
    for a, b in ((0, 1), (0, 2), (1, 2)):
        assert not torch.equal(ranks[a]["dirs"], ranks[b]["dirs"]), (a, b)
    torch.testing.assert_close(first_batch(1)["dirs"], ranks[1]["dirs"], rtol=0, atol=0)


def family_views(members: int = 5, frames: int = 3) -> tuple[SceneDataset, torch.Tensor]:
    """``frames`` photos of each of ``members`` members (the same camera rig), and the
    member of each photo."""
    one = views()
    n = members * frames
    data = SceneDataset(root=Path("family"), split="train",
                        images=torch.rand(n, 8, 8, 3, generator=torch.Generator().manual_seed(1)),
                        c2w=one.c2w[torch.arange(n) % 2], intrinsics=one.intrinsics,
                        env_index=torch.zeros(n, dtype=torch.long), env_names=["sky"],
                        envmaps=one.envmaps, bbox=one.bbox, ground_truth=None, spec=None)
    return data, torch.arange(members).repeat_interleave(frames)


def test_a_step_of_some_members_draws_the_same_members_on_every_rank():
    """With ``members_per_step`` each batch names M distinct members, sorted, and draws every
    ray from their photos, about evenly; the members follow the run's seed on every rank
    (their rays do not), change from step to step, and a resumed pass draws the same."""
    data, members = family_views()

    def batches(seed: int, skip: int = 0) -> list[dict]:
        rays = RandomRays(data, 600, 6, seed, members, members_per_step=2, member_seed=3)
        rays.resume_at(0, skip)
        return list(rays)

    ours, other_rank = batches(3), batches(rank_seed(3, 1))
    steps = [tuple(b["step_members"].tolist()) for b in ours]
    assert all(len(set(s)) == 2 and list(s) == sorted(s) for s in steps)
    assert len(set(steps)) > 1  # the members change from step to step
    for batch in ours:
        chosen = batch["step_members"]
        assert torch.isin(batch["member"], chosen).all()
        assert torch.equal(batch["member"].unique(), chosen)
        counts = torch.stack([(batch["member"] == k).sum() for k in chosen])
        assert (counts - 300).abs().max() < 5 * 300 ** 0.5 / 2  # binomial(600, 1/2): 5 sd
        img_of = (batch["rgb"][:, None, :] == data.images.reshape(1, -1, 3)).all(-1)
        assert img_of.any(-1).all()  # each ray's colour is a pixel of a photo
    assert [tuple(b["step_members"].tolist()) for b in other_rank] == steps
    assert not torch.equal(other_rank[0]["dirs"], ours[0]["dirs"])  # ranks' own rays
    for a, b in zip(batches(3, skip=4), ours[4:], strict=True):
        for key in a:
            assert torch.equal(a[key], b[key]), key


def test_without_members_per_step_the_batches_are_unchanged():
    """The default draws as a single scene does (the same numbers from the same seed), with
    each ray's member and no ``step_members``."""
    data, members = family_views()
    plain = next(iter(RandomRays(data, 64, 1, 3)))
    family = next(iter(RandomRays(data, 64, 1, 3, members)))
    assert "step_members" not in family
    for key, value in plain.items():
        assert torch.equal(family[key], value), key
    assert torch.equal(family["member"], members[(family["rgb"][:, None, :] ==
                                                   data.images.reshape(1, -1, 3)).all(-1)
                                                  .nonzero()[:, 1] // 64])


def test_metrics_are_means_over_the_ranks_but_clocks_and_memory():
    assert synced("train/loss") and synced("val/psnr") and synced("guard/nonfinite_grads")
    assert not synced("time/wall_s") and not synced("time/step_photo_s")
    assert not synced("memory/peak_rss_gib")


@pytest.mark.parametrize(("trainer", "count"), [
    ("cpu", 1), ("gpu", 1), ("ddp_cpu", 2)])
def test_the_trainer_configs_train_in_their_processes(trainer, count):
    assert processes(compose_config("train", ["preset=tiny", f"trainer={trainer}"])) == count


def test_process_count_reads_devices_nodes_and_strategy():
    ours = {"_target_": "nrt.distributed.GradientAveraging"}
    assert process_count({"strategy": ours, "devices": 3, "num_nodes": 2}) == 6
    assert process_count({"strategy": ours, "devices": [0, 2]}) == 2
    assert process_count({"strategy": "ddp", "devices": "4"}) == 4
    assert process_count({"strategy": None, "devices": 8}) == 1  # one device of 8


@pytest.mark.parametrize(("threads", "launcher", "processes", "cores", "expected"), [
    (None, None, 1, 16, None),                  # a lone run: torch's default
    (3, {"n_jobs": 4}, 2, 16, 3),               # given
    (None, {"n_jobs": 2}, 1, 2, 1),             # 2 jobs on 2 cores
    (None, {"n_jobs": 2}, 2, 16, 4),            # 2 jobs of 2 processes on 16 cores
    (None, {"n_jobs": -1}, 1, 4, 1),            # joblib's -1: a job per core
    (None, None, 2, 2, 1),                      # trainer=ddp_cpu on 2 cores
    (None, {"cpus_per_task": 1}, 1, 8, 1),      # submitit's cpus per job
    (None, {"cpus_per_task": 8, "tasks_per_node": 4}, 4, 64, 8),  # a SLURM task per rank
    (None, {"cpus_per_task": 8, "tasks_per_node": 1}, 2, 64, 4),  # Lightning starts 2
])
def test_a_job_gets_its_share_of_the_cores(threads, launcher, processes, cores, expected):
    assert job_threads(threads, launcher, processes, cores) == expected


@pytest.fixture
def hydra_job(tmp_path):
    """Hydra's config of a job (``nrt-train preset=tiny trainer=ddp_cpu ...`` whose folder is
    ``tmp_path/a=b,c``) set for the test, and taken back after it."""
    register_resolvers()
    with initialize_config_dir(config_dir=str(CONFIG_DIR), version_base="1.3"):
        cfg = compose("train", ["preset=tiny", "trainer=ddp_cpu", "init.ea_ckpt=/old.ckpt",
                                "budget.ea.steps=5"], return_hydra_config=True)
    with open_dict(cfg):
        cfg.hydra.runtime.output_dir = str(tmp_path / "a=b,c")
        cfg.hydra.runtime.cwd = str(tmp_path)
        cfg.hydra.job.name = "common"
    before = HydraConfig.instance().cfg
    HydraConfig.instance().set_config(cfg)
    yield tmp_path
    HydraConfig.instance().cfg = before


def test_a_rank_starts_as_the_job_with_rank_0s_folder_and_files(hydra_job):
    """The job's overrides (not rank 0's command line), rank 0's answers in place of the
    user's, rank 0's folder; no config copy; a log of its own. The overrides parse back to
    the same values, paths with ``=`` and ``,`` included."""
    pinned = {"init.ea_ckpt": "/runs/ea=1/last.ckpt", "resume": "/runs/x,y/last.ckpt",
              "threads": 1}
    command, cwd = child_command(1, pinned)
    assert command[:3] == [sys.executable, "-m", "nrt.cli.train"] and cwd == str(hydra_job)
    parsed = {o.key_or_group: o.value() for o in OverridesParser.create().parse_overrides(
        command[3:])}
    assert parsed == {"preset": "tiny", "trainer": "ddp_cpu", "budget.ea.steps": 5,
                      "init.ea_ckpt": "/runs/ea=1/last.ckpt", "resume": "/runs/x,y/last.ckpt",
                      "threads": 1, "hydra.run.dir": str(hydra_job / "a=b,c"),
                      "hydra.output_subdir": None, "hydra.job.name": "common_rank1"}


def rank(rank: int, world: int = 2, **more) -> SimpleNamespace:
    """A trainer as the callbacks see it on rank ``rank`` of ``world``."""
    return SimpleNamespace(global_rank=rank, world_size=world, **more)


@pytest.fixture
def generators():
    """The global generators, put back after the test."""
    kept = torch.get_rng_state(), random.getstate()
    yield
    torch.set_rng_state(kept[0])
    random.setstate(kept[1])


def draws_after(seed: int) -> torch.Tensor:
    """What torch's global generator draws first once seeded with ``seed``."""
    torch.manual_seed(seed)
    return torch.rand(3)


def test_a_new_run_keeps_rank_0s_generators_and_seeds_the_others(generators):
    expected = draws_after(11)
    torch.manual_seed(11)
    RandomState(seed=5).on_train_start(rank(0), None)
    assert torch.equal(torch.rand(3), expected)
    RandomState(seed=5).on_train_start(rank(1), None)
    drawn, drawn_python = torch.rand(3), random.random()
    random.seed(rank_seed(5, 1))
    assert torch.equal(drawn, draws_after(rank_seed(5, 1))) and drawn_python == random.random()


def test_a_resumed_rank_takes_its_own_generators_back(generators):
    """Each rank takes back its own generators from the checkpoint; one saved by another
    number of processes seeds the ranks it has no generators for."""
    states = []
    for seed in (21, 22):
        torch.manual_seed(seed)
        random.seed(seed)
        states.append(RandomState._own())
    checkpoint = {**states[0], "ranks": states}
    resumed = RandomState(seed=5)
    resumed.load_state_dict(checkpoint)
    resumed.on_train_start(rank(1), None)
    assert torch.equal(torch.rand(3), draws_after(22))
    other = RandomState(seed=5)
    other.load_state_dict(checkpoint)
    other.on_train_start(rank(2, world=3), None)  # saved by 2 processes, resumed in 3
    assert torch.equal(torch.rand(3), draws_after(rank_seed(5, 2)))


def test_ranks_go_by_rank_0s_clock_with_a_budget(monkeypatch):
    """With a budget and several ranks, schedules and the stop read the clock rank 0
    broadcast at the end of the last step: a rank whose own clock lags stops with it."""
    now = [0.0]
    monkeypatch.setattr("nrt.callbacks.time.perf_counter", lambda: now[0])
    clock = WallClock(budget_s=10.0)
    trainer = rank(1, callbacks=[clock], max_steps=1000, global_step=0, should_stop=False,
                   strategy=SimpleNamespace(broadcast=lambda value: 12.0))
    module = SimpleNamespace(log=lambda *args, **kwargs: None)
    clock.on_train_start(trainer, module)
    now[0] = 4.0
    assert training_progress(trainer) == 0.0  # rank 0's clock at the start
    clock.on_train_batch_end(trainer, module, None, None, 0)
    assert clock.schedule_seconds() == 12.0 and clock.seconds() == 4.0
    assert trainer.should_stop and training_progress(trainer) == 1.0
    alone = WallClock(budget_s=10.0)  # one process: its own clock, as before
    alone.on_train_start(rank(0, world=1), module)
    assert alone.schedule_seconds() == alone.seconds() == 0.0
