"""``nrt-data`` as users run it: the installed console script in a subprocess."""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
import time
from pathlib import Path

import pytest
from omegaconf import OmegaConf

pytestmark = pytest.mark.e2e

# A render of a few pixels, so that the first (rendering) call stays quick.
SMALL = ("scene.cameras.num_train=2", "scene.cameras.num_test=1", "scene.cameras.width=8",
         "scene.cameras.height=8", "scene.spp=4", "scene.medium.resolution=8")


def console_script(name: str) -> str:
    beside = Path(sys.executable).with_name(name)  # the interpreter's own bin/ first
    found = str(beside) if beside.is_file() else shutil.which(name)
    if found is None:
        pytest.fail(f"console script '{name}' is not installed; run `pip install -e .`")
    return found


def nrt_data(*args: str, cwd: Path, wait: bool = True, timeout: float = 120):
    """Run ``nrt-data args`` in ``cwd`` (``wait=False``: start it and return a callable
    that waits for it). Datasets and logs go to ``cwd/outputs`` (NRT_OUTPUT_DIR) unless
    ``paths.output_dir`` says otherwise, never into the repository."""
    env = {k: v for k, v in os.environ.items() if k != "HYDRA_FULL_ERROR"}
    env["NRT_OUTPUT_DIR"] = str(cwd / "outputs")
    cmd = [console_script("nrt-data"), *args]
    proc = subprocess.Popen(cmd, cwd=cwd, env=env, stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True)

    def finish() -> subprocess.CompletedProcess:
        try:
            out, err = proc.communicate(timeout=timeout)
        except subprocess.TimeoutExpired:
            proc.kill()
            raise
        return subprocess.CompletedProcess(cmd, proc.returncode, out, err)

    return finish() if wait else finish


def file_times(folder: Path) -> dict[str, int]:
    return {str(p.relative_to(folder)): p.stat().st_mtime_ns for p in folder.rglob("*")}


MISTAKES = {"medium.num_elements": "scene.medium.num_elements=9",
            "cameras.radius": "scene.cameras.radius=1.0"}


@pytest.fixture(scope="module")
def runs(tiny_dataset, tiny_output_dir, tmp_path_factory) -> dict:
    """The independent invocations, started together (they mostly wait on imports) and
    collected once all have finished: ``{name: (CompletedProcess, its working folder)}``,
    and ``tiny_files`` (the session dataset's file times before they ran)."""
    started = {}
    tiny_files = file_times(tiny_dataset)

    def start(name: str, *args: str) -> None:
        cwd = tmp_path_factory.mktemp(f"cli_{name.replace('.', '_')}")
        started[name] = (nrt_data(*args, cwd=cwd, wait=False), cwd)

    start("session", "preset=tiny", f"paths.output_dir={tiny_output_dir}")
    start("unknown_key", "foo=1")
    start("cfg_job", "--cfg", "job", "preset=tiny", "scene=isotropic")
    for key, override in MISTAKES.items():
        start(key, "preset=tiny", override)
    done = {name: (finish(), cwd) for name, (finish, cwd) in started.items()}
    return {**done, "tiny_files": tiny_files}


@pytest.mark.slow  # CLI processes (~6-8 s): keeps the fast tier under 3 minutes
def test_renders_once_then_reuses_the_cached_folder(tmp_path):
    out = tmp_path / "out"
    args = ("preset=tiny", *SMALL, "render.progress=false", f"paths.output_dir={out}")
    first = nrt_data(*args, cwd=tmp_path)
    assert first.returncode == 0, first.stderr
    folder = Path(first.stdout.strip())  # stdout is the folder alone: DATA=$(nrt-data ...)
    assert folder.parent == out / "datasets" and folder.name.startswith("default-")
    assert (folder / "scene.json").is_file() and (folder / "transforms_test.json").is_file()
    assert "Rendered 9 images" in first.stderr  # 2 + 1 views under each of 3 skies
    before = file_times(folder)

    start = time.perf_counter()
    second = nrt_data(*args, cwd=tmp_path)
    seconds = time.perf_counter() - start
    assert second.returncode == 0, second.stderr
    assert second.stdout == first.stdout
    assert "up to date" in second.stderr
    assert "Rendered" not in second.stderr and "variant" not in second.stderr  # no Mitsuba
    assert file_times(folder) == before
    assert seconds < 30, seconds
    assert not (tmp_path / "outputs").exists()


def test_finds_the_dataset_rendered_in_process(runs, tiny_dataset):
    """The CLI and a config composed in Python resolve the same spec, hence one folder."""
    proc, _ = runs["session"]
    assert proc.returncode == 0, proc.stderr
    assert proc.stdout.strip() == str(tiny_dataset)
    assert "up to date" in proc.stderr
    assert file_times(tiny_dataset) == runs["tiny_files"]


def test_unknown_key_is_one_paragraph_and_exit_status_2(runs):
    proc, cwd = runs["unknown_key"]
    assert proc.returncode == 2, proc.stderr
    assert "nrt: error: foo=1: the config has no key 'foo'" in proc.stderr
    assert "+foo=<value>" in proc.stderr and "nrt-data --cfg job" in proc.stderr
    assert "Traceback" not in proc.stderr
    assert not (cwd / "outputs" / "datasets").exists()


def test_cfg_job_prints_the_composed_config(runs):
    proc, cwd = runs["cfg_job"]
    assert proc.returncode == 0, proc.stderr
    cfg = OmegaConf.create(proc.stdout)
    assert cfg.task == "data" and cfg.scene.name == "isotropic"
    assert cfg.scene.effects.phase == "isotropic"
    assert cfg.scene.cameras.num_train == 16 and cfg.scene.cameras.width == 32
    assert "hydra" not in cfg
    assert not (cwd / "outputs").exists()  # nothing rendered


@pytest.mark.parametrize("key", list(MISTAKES))
def test_user_mistake_is_one_paragraph_and_exit_status_2(runs, key):
    assert_refused_before_rendering(*runs[key], key)


def assert_refused_before_rendering(proc: subprocess.CompletedProcess, cwd: Path, key: str
                                    ) -> None:
    """``nrt-data`` ended with one ``nrt: error:`` paragraph naming ``scene.<key>``, exit
    status 2, nothing rendered, and the error kept in the run's log."""
    assert proc.returncode == 2, (proc.stdout, proc.stderr)
    assert "Traceback" not in proc.stderr + proc.stdout
    assert proc.stdout == ""
    errors = [line for line in proc.stderr.splitlines() if line.startswith("nrt: error:")]
    assert len(errors) == 1, proc.stderr
    assert f"'scene.{key}'" in errors[0]  # the key as users type it
    assert proc.stderr.count(errors[0][len("nrt: error: "):]) == 1  # said once, not twice
    data_dir = cwd / "outputs" / "datasets"
    leftovers = [p.name for p in data_dir.iterdir() if p.name != "logs"]
    assert leftovers == []  # no half-rendered dataset left behind
    log_files = list((data_dir / "logs").rglob("*.log"))
    assert any(key in p.read_text() for p in log_files)  # the run's log keeps the error
