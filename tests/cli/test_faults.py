"""Faults and misuse: names that would leave the output folder, output folders that cannot
take files, a full disk, a process killed while it writes a checkpoint or renders a
dataset, and resumed runs that must be the same run.

A full disk is a real one: a small tmpfs mounted in a private mount namespace
(``unshare``); the tests that need it are skipped where the machine allows no namespace.
"""

from __future__ import annotations

import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from nrt.errors import ConfigError, SceneError, WriteError
from nrt.files import TEMP_MARK, atomic_write, check_name, check_output_folder
from tests.conftest import (
    ROOT,
    cli_in_process,
    compose_config,
    kill_after_checkpoint,
    only_run_dir,
    refusal,
    run_train,
    train_command,
)

pytestmark = pytest.mark.e2e

FAST_RENDER = ("preset=tiny", "scene.cameras.num_train=2", "scene.cameras.num_test=1",
               "scene.cameras.width=8", "scene.cameras.height=8", "scene.spp=4",
               "scene.medium.resolution=8", "render.progress=false")
"""A dataset of a few pixels (nrt-data renders it in about a second)."""


def nrt(command: str, *args: str, cwd: Path, **popen) -> subprocess.Popen:
    """Start ``nrt-<command> args`` in ``cwd``, outputs under ``cwd/outputs``."""
    env = {k: v for k, v in os.environ.items() if k != "HYDRA_FULL_ERROR"}
    env["NRT_OUTPUT_DIR"] = str(cwd / "outputs")
    return subprocess.Popen([sys.executable, "-m", f"nrt.cli.{command}", *args], cwd=cwd,
                            env=env, text=True, stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, **popen)


def nrt_in_process(command: str, *args: str, cwd: Path) -> subprocess.CompletedProcess:
    """:func:`nrt`'s command run to its end in the test's process (for refusals)."""
    return cli_in_process(command, *args, cwd=cwd, env={"NRT_OUTPUT_DIR": str(cwd / "outputs")})


def finished(proc: subprocess.Popen, timeout: float = 300) -> subprocess.CompletedProcess:
    out, err = proc.communicate(timeout=timeout)
    return subprocess.CompletedProcess(proc.args, proc.returncode, out, err)


def tree(folder: Path) -> set[str]:
    return {str(p.relative_to(folder)) for p in folder.rglob("*")}


# ---------------------------------------------------------------- names and folders
@pytest.mark.parametrize("name", ["../../somewhere", "a/b", "..", ".hidden", "-x", "", "a b",
                                  "/abs", "x" * 129])
def test_a_name_that_could_leave_its_folder_is_refused(name):
    with pytest.raises(ConfigError, match=r"scene\.name=.*a name that becomes a folder name"):
        check_name("scene.name", name)
    with pytest.raises(SceneError, match=r"scene\.name"):
        check_name("scene.name", name, SceneError)


@pytest.mark.parametrize("name", ["default", "heldout2", "my_scene-1.v2", "cloud+sun", "3"])
def test_plain_names_pass(name):
    assert check_name("scene.name", name) == name


@pytest.mark.parametrize(("command", "override", "key"), [
    ("train", "scene.name=../../somewhere", "scene.name"),
    ("train", "stage.name=../x", "stage.name"),
    ("data", "scene.name=../../somewhere", "scene.name"),
])
def test_a_name_leaving_the_output_folder_writes_nothing(tmp_path, command, override, key):
    """``nrt-train scene.name=../../somewhere`` would write its dataset and run folders
    outside the output folder; it is refused before any folder is made."""
    work = tmp_path / "a" / "b"
    work.mkdir(parents=True)
    proc = nrt_in_process(command, "preset=tiny", override, cwd=work)
    assert refusal(proc.returncode, proc.stderr).startswith(f"nrt: error: {key}=")
    outside = {p for p in tree(tmp_path) if not p.startswith("a/b/outputs/datasets/logs")}
    assert outside <= {"a", "a/b", "a/b/outputs", "a/b/outputs/datasets"}  # nrt-data's log


def test_an_output_folder_that_is_a_file_is_refused_before_anything(tmp_path):
    (tmp_path / "taken").write_text("a file")
    for command, key in (("train", "paths.output_dir"), ("data", "paths.data_dir")):
        proc = nrt_in_process(command, "preset=tiny", f"paths.output_dir={tmp_path}/taken/out",
                              cwd=tmp_path)
        line = refusal(proc.returncode, proc.stderr)
        assert line.startswith(f"nrt: error: {key}:") and "is a file, not a folder" in line
    assert tree(tmp_path) == {"taken"}
    with pytest.raises(ConfigError, match="paths.data_dir"):
        check_output_folder(tmp_path / "taken", "paths.data_dir")
    check_output_folder(tmp_path / "new" / "deeper", "paths.output_dir")  # creatable


@pytest.mark.parametrize("override", ["seed=abc", "seed=-1", "seed=4294967296", "seed=1.5",
                                      "resume=3", "budget_s=-5", "budget_s=soon",
                                      "threads=0", "threads=two", "compile=maybe"])
def test_scalar_options_are_refused_like_the_budget(override):
    from nrt.cli.checks import check_options

    key, value = override.split("=", 1)
    with pytest.raises(ConfigError, match=rf"^{key}=.*: must be .*--cfg job"):
        check_options(compose_config("train", ["preset=tiny", override]))


def test_seed_abc_is_one_paragraph_before_any_folder(tmp_path):
    proc = nrt_in_process("train", "preset=tiny", "seed=abc", cwd=tmp_path)
    assert refusal(proc.returncode, proc.stderr).startswith("nrt: error: seed=abc: must be")
    assert not (tmp_path / "outputs").exists()


# ---------------------------------------------------------------- atomic writes
def test_a_failed_atomic_write_keeps_the_old_file(tmp_path):
    target = tmp_path / "last.ckpt"
    target.write_bytes(b"complete")
    with pytest.raises(RuntimeError), atomic_write(target, "the checkpoint") as f:
        f.write(b"half")
        raise RuntimeError("killed")
    assert target.read_bytes() == b"complete" and os.listdir(tmp_path) == ["last.ckpt"]
    with pytest.raises(WriteError, match=r"could not write the checkpoint '.*gone/x.ckpt'"):
        with atomic_write(tmp_path / "gone" / "x.ckpt", "the checkpoint") as f:
            f.write(b"x")


KILL_WRITER = """
import sys, torch
from nrt.files import atomic_write
big = {"w": torch.randn(4_000_000)}  # 16 MB: its write takes long enough to be caught
while True:
    with atomic_write(sys.argv[1], "the checkpoint") as f:
        torch.save(big, f)
"""


def test_killed_while_writing_a_checkpoint_leaves_a_loadable_last_ckpt(tmp_path):
    """SIGKILL while the checkpoint's temporary file is being written: ``last.ckpt`` stays
    the previous, complete checkpoint."""
    import torch

    last = tmp_path / "last.ckpt"
    torch.save({"global_step": 7}, last)
    proc = subprocess.Popen([sys.executable, "-c", KILL_WRITER, str(last)], cwd=ROOT)
    temp = tmp_path / f".last.ckpt{TEMP_MARK}{proc.pid}"
    try:
        deadline = time.time() + 60
        while not temp.exists() and time.time() < deadline:
            time.sleep(0.001)
        assert temp.exists(), "the writer never started a checkpoint"
    finally:
        proc.send_signal(signal.SIGKILL)
        proc.wait()
    loaded = torch.load(last, weights_only=False)
    assert set(loaded) in ({"global_step"}, {"w"})  # the old one, or a complete new one
    if "w" in loaded:
        assert loaded["w"].shape == (4_000_000,)


# ---------------------------------------------------------------- CLI: slow tier
@pytest.mark.slow  # trains until a kill (~15-25 s)
def test_nrt_train_killed_during_a_checkpoint_write_resumes(tmp_path, tiny_dataset):
    """The real ``nrt-train`` with a checkpoint every step, killed while its ``last.ckpt``
    is being replaced: the file loads, and ``resume=true`` continues from it in the same
    folder, its training clock going on, the first run's config kept and the resumed run's
    config and log written beside it."""
    import torch

    cmd, env = train_command(tmp_path, tiny_dataset.parent, "logger=csv",
                             "budget.ea.steps=100000", "budget.checkpoint_every=1",
                             "budget.val_every=1000")
    proc = subprocess.Popen(cmd, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    caught = None
    try:
        deadline = time.time() + 240
        while caught is None and time.time() < deadline:
            for ckpts in tmp_path.glob("default/ea/*/checkpoints"):
                if (ckpts / "last.ckpt").exists():
                    caught = next(iter(ckpts.glob(f".last.ckpt{TEMP_MARK}*")), None)
            time.sleep(0.0005)
    finally:
        proc.send_signal(signal.SIGKILL)
        proc.wait()
    assert caught is not None, "never caught a checkpoint being written"
    run = only_run_dir(tmp_path, "ea")
    saved = torch.load(run / "checkpoints" / "last.ckpt", weights_only=False, map_location="cpu")
    step, clock = saved["global_step"], saved["callbacks"]["WallClock"]["elapsed"]
    assert step >= 1
    done = run_train(tmp_path, tiny_dataset.parent, "logger=csv", "resume=true",
                     f"budget.ea.steps={step + 20}", "budget.checkpoint_every=1",
                     "budget.val_every=1000")
    assert done.returncode == 0, done.stderr[-3000:]
    assert only_run_dir(tmp_path, "ea") == run  # continued in place, no new run folder
    resumed = torch.load(run / "checkpoints" / "last.ckpt", weights_only=False,
                         map_location="cpu")
    assert resumed["global_step"] == step + 20
    assert resumed["callbacks"]["WallClock"]["elapsed"] > clock
    assert "budget.ea.steps=100000" in (run / ".hydra" / "overrides.yaml").read_text()
    assert list(run.glob(".hydra/resumed-*/overrides.yaml"))
    assert list(run.glob("csv/resumed-*/metrics.csv"))


@pytest.mark.slow  # two renders (~10 s)
def test_a_render_killed_halfway_is_never_taken_for_a_dataset(tmp_path):
    """``nrt-data`` killed while it renders leaves no folder the cache takes for complete:
    the next ``nrt-data`` renders the dataset in full."""
    args = (*FAST_RENDER, "scene.cameras.num_train=40", "scene.cameras.width=24",
            "scene.cameras.height=24", "scene.spp=16")
    proc = nrt("data", *args, cwd=tmp_path)
    data = tmp_path / "outputs" / "datasets"
    try:
        deadline = time.time() + 120
        while time.time() < deadline and not list(data.glob(f".*{TEMP_MARK}*/images/*/*.exr")):
            time.sleep(0.01)
        assert list(data.glob(f".*{TEMP_MARK}*/images/*/*.exr")), "no render started"
    finally:
        proc.send_signal(signal.SIGKILL)
        proc.wait()
    assert not [p for p in data.iterdir() if TEMP_MARK not in p.name and p.name != "logs"]
    again = finished(nrt("data", *args, cwd=tmp_path))
    assert again.returncode == 0, again.stderr[-3000:]
    folder = Path(again.stdout.strip())
    assert (folder / "scene.json").is_file() and folder.parent == data
    frames = [*folder.glob("images/*/train_*.exr")]
    assert len(frames) == 40 * 3


@pytest.mark.slow  # two renders at once (~10 s)
def test_concurrent_renders_of_one_scene_end_with_one_complete_dataset(tmp_path):
    procs = [nrt("data", *FAST_RENDER, cwd=tmp_path) for _ in range(2)]
    done = [finished(p) for p in procs]
    assert all(d.returncode == 0 for d in done), [d.stderr[-2000:] for d in done]
    folders = {d.stdout.strip() for d in done}
    assert len(folders) == 1
    folder = Path(folders.pop())
    assert (folder / "scene.json").is_file()
    assert len(list(folder.glob("images/*/*.exr"))) == 3 * 3
    assert sorted(p.name for p in folder.parent.iterdir()) == [folder.name, "logs"]


UNSHARE = shutil.which("unshare")


def in_private_mounts(script: str, cwd: Path) -> subprocess.CompletedProcess:
    """Run ``script`` (sh) in a mount namespace of its own, as root there, where it can
    mount a small tmpfs; skips the test where the machine allows no such namespace."""
    if UNSHARE is None or subprocess.run([UNSHARE, "-rm", "true"]).returncode != 0:
        pytest.skip("no user and mount namespaces here (unshare -rm)")
    env = {k: v for k, v in os.environ.items() if k != "HYDRA_FULL_ERROR"}
    return subprocess.run([UNSHARE, "-rm", "sh", "-ec", script], cwd=cwd, env=env, text=True,
                          capture_output=True, timeout=600)


@pytest.mark.slow  # two short EA runs and a render (~60 s)
def test_a_full_disk_is_a_clear_error_and_resume_continues(tmp_path, tiny_dataset):
    """A real full disk (an 8 MiB tmpfs holds one 5 MiB checkpoint of the tiny EA stage, not
    its replacement beside it): the run ends with one ``nrt: error:`` naming the checkpoint
    and no traceback, the last checkpoint loads, and ``resume=true`` finishes the run once
    the disk has room. A read-only folder and a dataset render on a full disk are refused
    the same way."""
    import torch

    disk, small, logs = tmp_path / "disk", tmp_path / "small", tmp_path / "logs"
    for folder in (disk, small, logs):
        folder.mkdir()
    cmd, _ = train_command(disk / "out", tiny_dataset.parent, "logger=csv",
                           "budget.ea.steps=40", "budget.checkpoint_every=10",
                           "budget.val_every=20")
    train = " ".join(f"'{c}'" for c in cmd)
    data = f"'{sys.executable}' -m nrt.cli.data {' '.join(FAST_RENDER)}"
    script = f"""
mount -t tmpfs -o size=8m tmpfs {disk}
set +e
NRT_OUTPUT_DIR={disk}/out {train} > {logs}/full.out 2> {logs}/full.err; echo $? > {logs}/full.rc
cp {disk}/out/default/ea/*/checkpoints/last.ckpt {logs}/last.ckpt
mount -o remount,size=64m {disk}
NRT_OUTPUT_DIR={disk}/out {train} resume=true > {logs}/resumed.out 2> {logs}/resumed.err
echo $? > {logs}/resumed.rc
ls {disk}/out/default/ea/*/density_grid.npz > {logs}/exports
mount -t tmpfs -o size=16k tmpfs {small}
NRT_OUTPUT_DIR={small} {data} > {logs}/data.out 2> {logs}/data.err; echo $? > {logs}/data.rc
ls -a {small}/datasets > {logs}/datasets
mount -o remount,ro {disk}
NRT_OUTPUT_DIR={disk}/ro {train} > {logs}/ro.out 2> {logs}/ro.err; echo $? > {logs}/ro.rc
"""
    ran = in_private_mounts(script, tmp_path)
    assert ran.returncode == 0, ran.stderr[-3000:]

    def read(name: str) -> str:
        return (logs / name).read_text()

    line = refusal(int(read("full.rc")), read("full.err"))
    assert "could not write the checkpoint" in line and "No space left on device" in line
    assert "resume=true" in line
    assert torch.load(logs / "last.ckpt", weights_only=False)["global_step"] == 10
    assert read("resumed.rc").strip() == "0", read("resumed.err")[-3000:]
    assert read("exports").strip().endswith("density_grid.npz")
    line = refusal(int(read("data.rc")), read("data.err"))
    assert "could not write the dataset of scene 'default'" in line
    assert "No space left on device" in line
    assert set(read("datasets").split()) <= {".", "..", "logs"}  # the partial render is gone
    line = refusal(int(read("ro.rc")), read("ro.err"))
    assert line.startswith("nrt: error: paths.output_dir:") and "not writable" in line


@pytest.mark.slow  # the session's EA run, then two short runs and a resume (~40 s each)
@pytest.mark.parametrize(("stage", "export", "keys"), [
    ("rte", "medium_grids.npz", ("sigma_a", "sigma_s", "g")),
    ("ea", "density_grid.npz", ("density",)),
])
def test_a_run_resumed_after_a_kill_ends_the_same(tmp_path, tiny_ea_run, stage, export, keys):
    """Stages 1 and 2 are deterministic for a seed (and stage 2 for an EA checkpoint): a run
    killed after a checkpoint, whether the checkpoint falls on a validation or between two,
    and resumed with ``resume=true`` exports the same grids, bit for bit, as the same run
    left alone."""
    ea_out, ea = tiny_ea_run
    assert ea.returncode == 0, ea.stderr[-3000:]
    ea_ckpt = only_run_dir(ea_out, "ea") / "checkpoints" / "last.ckpt"
    steps = (f"budget.{stage}.steps=60", "budget.checkpoint_every=10", "budget.val_every=20",
             f"init.ea_ckpt={ea_ckpt}", "logger=csv")
    data = ea_out / "datasets"
    whole_out, cut_out = tmp_path / "whole", tmp_path / "cut"
    whole = run_train(whole_out, data, *steps, stage=stage)
    assert whole.returncode == 0, whole.stderr[-3000:]
    cmd, env = train_command(cut_out, data, *steps, stage=stage)
    proc = subprocess.Popen(cmd, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    saved = kill_after_checkpoint(proc, cut_out, f"default/{stage}/*/checkpoints/last.ckpt",
                                  10, 50)
    assert not list(cut_out.glob(f"default/{stage}/*/{export}"))  # it was cut short
    resumed = run_train(cut_out, data, *steps, "resume=true", stage=stage)
    assert resumed.returncode == 0, resumed.stderr[-3000:]
    a = np.load(only_run_dir(whole_out, stage) / export)
    b = np.load(only_run_dir(cut_out, stage) / export)
    for key in keys:
        np.testing.assert_array_equal(a[key], b[key], err_msg=f"{key} (killed at {saved})")
