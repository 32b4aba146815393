"""Shared fixtures: configs composed from the real conf/ tree, and the ``tiny`` dataset of
the default scene, rendered once per pytest run and reused by every test that reads it;
and the check of the tier markers (``unit``, ``integration``, ``e2e``; ``gpu`` skips without
CUDA)."""

from __future__ import annotations

import os

# As the nrt commands do (nrt.cli.common.run_app): idle OpenMP threads sleep instead of
# spinning, so tests and the subprocesses they start do not starve each other.
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

import contextlib
import copy
import csv
import json
import signal
import subprocess
import sys
import time
from collections.abc import Callable
from pathlib import Path

import pytest
import torch
from filelock import FileLock
from hydra import compose, initialize_config_dir
from omegaconf import DictConfig, OmegaConf

from nrt.cli.common import CONFIG_DIR, register_resolvers
from nrt.compile import EXTENSIONS_DIR_ENV, LazyExtension, extensions_dir
from nrt.data.render import ensure_dataset

# The fused C++ kernels (on by default) are built once per machine and shared by the tests and
# the nrt commands they start, not once in each command's fresh output folder (~35 s each).
os.environ.setdefault(EXTENSIONS_DIR_ENV, str(extensions_dir()))

ROOT = Path(__file__).resolve().parent.parent
"""The repository's root, which holds ``nrt/``, ``benchmarks/`` and ``conf/``."""


def compose_config(config_name: str = "dataset", overrides: list[str] | tuple = ()) -> DictConfig:
    """``conf/<config_name>.yaml`` with ``overrides``, composed as the CLI composes it."""
    register_resolvers()
    with initialize_config_dir(config_dir=str(CONFIG_DIR), version_base="1.3"):
        return compose(config_name, overrides=list(overrides))


TIERS = ("unit", "integration", "e2e")
"""The tier markers (pyproject.toml); a module sets its tests' one tier with ``pytestmark``."""


def pytest_collection_modifyitems(items: list[pytest.Item]) -> None:
    """Refuses a test without exactly one tier marker, and skips ``gpu`` tests where torch
    sees no CUDA device."""
    wrong = []
    for item in items:
        tiers = {m.name for m in item.iter_markers() if m.name in TIERS}
        if len(tiers) != 1:
            wrong.append(f"{item.nodeid}: {sorted(tiers) or 'none'}")
    if wrong:
        raise pytest.UsageError(
            f"a test needs exactly one tier marker of {', '.join(TIERS)} "
            "(pytestmark in its module); found:\n" + "\n".join(wrong)
        )
    gpu = [item for item in items if item.get_closest_marker("gpu")]
    if gpu:
        import torch

        if not torch.cuda.is_available():
            skip = pytest.mark.skip(reason="needs CUDA, and torch sees no CUDA device here")
            for item in gpu:
                item.add_marker(skip)


_scenes: dict[tuple[str, ...], dict] = {}


@pytest.fixture
def scene_config() -> Callable[..., dict]:
    """Factory: the resolved ``scene`` group (a fresh plain dict) of ``preset=tiny`` and
    ``overrides``. Compositions are cached per session (Hydra takes ~0.15 s each)."""

    def make(*overrides: str) -> dict:
        if overrides not in _scenes:
            cfg = compose_config("dataset", ["preset=tiny", *overrides])
            _scenes[overrides] = OmegaConf.to_container(cfg.scene, resolve=True)
        return copy.deepcopy(_scenes[overrides])

    return make


def session_folder(tmp_path_factory, name: str) -> Path:
    """A folder the session's shared fixtures build in: under pytest-xdist (``-n 2``) one
    folder that every worker sees (the workers' temporary folders share a parent), else a
    fresh one. Build in it under :func:`building`."""
    if os.environ.get("PYTEST_XDIST_WORKER") is None:
        return tmp_path_factory.mktemp(name)
    folder = tmp_path_factory.getbasetemp().parent / name
    folder.mkdir(exist_ok=True)
    return folder


@contextlib.contextmanager
def building(folder: Path):
    """Held while a session fixture builds ``folder``: the first worker builds, the others
    wait and then find it built (the builders below skip what is already there)."""
    with FileLock(str(folder) + ".lock"):
        yield


@pytest.fixture(scope="session")
def tiny_output_dir(tmp_path_factory) -> Path:
    """``paths.output_dir`` of the session's tiny dataset (datasets live in ``datasets/``)."""
    return session_folder(tmp_path_factory, "nrt_output")


@pytest.fixture(scope="session")
def tiny_dataset(tiny_output_dir) -> Path:
    """Folder of the default scene's ``tiny`` dataset (16 train + 4 test views of 32x32
    under each of three skies), rendered with Mitsuba once per session. Treat it as read-only: tests
    that corrupt a dataset copy it first."""
    cfg = compose_config("dataset", ["preset=tiny", f"paths.output_dir={tiny_output_dir}"])
    scene = OmegaConf.to_container(cfg.scene, resolve=True)
    with building(tiny_output_dir):
        folder = ensure_dataset(scene, cfg.paths.data_dir, progress=False)
    assert (folder / "scene.json").is_file(), folder
    return folder


ONE_SKY = ("scene.environments.sky_seeds=[0]", "scene.environments.train=[0]")
"""The tiny scene under one sky: the in-process tests of a stage's mechanics render a third
of the tiny preset's images (three skies, two trained on). The several-skies path has its
own tests (test_rte_split_stage.py, test_dpt_stage.py) and the CLI tests run the preset."""


GENERATIVE_FAMILY = ("preset=tiny", "scene=family", "mode=generative")
SMALL_FAMILY = ("scene.cameras.num_train=8", "scene.cameras.num_test=2",
                "scene.cameras.width=24", "scene.cameras.height=24", "scene.spp=16")
"""The family the generative tests render (K = 4 members of 10 views of 24 x 24 pixels under
each of the two skies): a third of the tiny preset's pixels, enough to tell the members
apart."""


@pytest.fixture(scope="session")
def family_dir(tmp_path_factory) -> Path:
    """The test family (:data:`SMALL_FAMILY`), rendered once per session: its folder
    (``family.json``); ``paths.output_dir`` is its grandparent. Read-only."""
    out = session_folder(tmp_path_factory, "generative")
    cfg = compose_config("train", [*GENERATIVE_FAMILY, *SMALL_FAMILY,
                                   f"paths.output_dir={out}"])
    from nrt.data.family import ensure_family

    with building(out):
        return ensure_family(OmegaConf.to_container(cfg.scene, resolve=True),
                             cfg.paths.data_dir, progress=False)


NRT_TRAIN = [sys.executable, "-m", "nrt.cli.train"]


def train_command(out: Path, data_root: Path, *overrides: str, stage: str = "ea"
                  ) -> tuple[list[str], dict]:
    """``nrt-train stage=<stage> preset=tiny`` writing runs under ``out`` and reading the
    session's cached tiny dataset from ``data_root`` (no re-render)."""
    env = {**os.environ, "NRT_OUTPUT_DIR": str(out)}
    return [*NRT_TRAIN, f"stage={stage}", "preset=tiny", "logger=[tensorboard,csv]",
            f"paths.data_dir={data_root}", "render.progress=false",
            "trainer.enable_progress_bar=false", *overrides], env


def run_train(out: Path, data_root: Path, *overrides: str, stage: str = "ea"
              ) -> subprocess.CompletedProcess:
    cmd, env = train_command(out, data_root, *overrides, stage=stage)
    return subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=600)


def cli_in_process(command: str, *args: str, env: dict | None = None, cwd: Path | None = None
                   ) -> subprocess.CompletedProcess:
    """``nrt-<command> args`` run inside the test's process with ``env`` added to the
    environment (in the working folder ``cwd``, when given): its exit status and what it
    printed, as :func:`subprocess.run` gives them.
    For commands that refuse their input: a refusal then costs a config composition instead
    of a Python start (~6 s on 2 cores). The process's environment, arguments, logging and
    Hydra's global state and the working folder are restored afterwards."""
    import contextlib
    import importlib
    import io
    import logging
    import traceback

    from hydra.core.global_hydra import GlobalHydra

    from nrt import run_dirs

    main = importlib.import_module(f"nrt.cli.{command}").main
    root = logging.getLogger()
    saved = (dict(os.environ), sys.argv, list(root.handlers), root.level,
             dict(run_dirs._chosen), os.getcwd())
    out, err, status = io.StringIO(), io.StringIO(), 0
    try:
        os.environ.pop("HYDRA_FULL_ERROR", None)  # unset, as a user's shell has it
        os.environ.update({"NRT_KEEP_MALLOC": "1", **(env or {})})
        sys.argv = [f"nrt-{command}", *args]
        if cwd is not None:
            os.chdir(cwd)
        run_dirs._chosen.clear()  # a new process's: the run folder is chosen anew
        GlobalHydra.instance().clear()
        with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
            try:
                main()
            except SystemExit as exc:
                status = exc.code if isinstance(exc.code, int) else (exc.code is not None)
                if isinstance(exc.code, str):
                    print(exc.code, file=sys.stderr)
            except Exception:  # what an uncaught error prints, and its status
                traceback.print_exc()
                status = 1
    finally:
        environ, sys.argv, handlers, level, chosen, folder = saved
        os.chdir(folder)
        os.environ.clear()
        os.environ.update(environ)
        for handler in set(root.handlers) - set(handlers):
            handler.close()
        root.handlers[:], root.level = handlers, level
        run_dirs._chosen.clear()
        run_dirs._chosen.update(chosen)
        GlobalHydra.instance().clear()
    return subprocess.CompletedProcess([f"nrt-{command}", *args], int(status),
                                       out.getvalue(), err.getvalue())


def train_in_process(out: Path, data_root: Path, *overrides: str, stage: str = "ea"
                     ) -> subprocess.CompletedProcess:
    """:func:`run_train`'s command in the test's process (:func:`cli_in_process`): for
    refusals."""
    cmd, _ = train_command(out, data_root, *overrides, stage=stage)
    return cli_in_process("train", *cmd[len(NRT_TRAIN):], env={"NRT_OUTPUT_DIR": str(out)})


def multirun_command(out: Path, data_root: Path, *overrides: str, stage: str = "ea"
                     ) -> tuple[list[str], dict]:
    """:func:`train_command` as a sweep: ``nrt-train -m ...``."""
    cmd, env = train_command(out, data_root, *overrides, stage=stage)
    return [*cmd[:3], "-m", *cmd[3:]], env


def multirun(out: Path, data_root: Path, *overrides: str, env: dict | None = None
             ) -> subprocess.CompletedProcess:
    """``nrt-train -m stage=ea preset=tiny ...`` (:func:`multirun_command`), finished;
    ``env``: variables added to its environment."""
    cmd, base = multirun_command(out, data_root, *overrides)
    return subprocess.run(cmd, env={**base, **(env or {})}, capture_output=True, text=True,
                          timeout=600)


def kill_after_checkpoint(proc: subprocess.Popen, folder: Path, pattern: str, first: int,
                          end: int, timeout: float = 300) -> int:
    """Wait until a ``last.ckpt`` of ``folder.glob(pattern)`` holds a step in [first, end),
    then kill ``proc`` (SIGKILL, as a crash or a preemption would); that step."""
    import torch

    try:
        deadline, saved = time.time() + timeout, None
        while time.time() < deadline and saved is None:
            for last in folder.glob(pattern):
                step = torch.load(last, weights_only=False, map_location="cpu")["global_step"]
                saved = step if first <= step < end else None
            time.sleep(0.05)
        assert saved is not None, f"no checkpoint at a step in [{first}, {end})"
    finally:
        proc.send_signal(signal.SIGKILL)
        proc.wait()
    return saved


def refusal(returncode: int, stderr: str) -> str:
    """The one ``nrt: error:`` line of a command that refused its input as a user error:
    status 2, one such line, no traceback."""
    assert returncode == 2, stderr[-2000:]
    errors = [line for line in stderr.splitlines() if line.startswith("nrt: error:")]
    assert len(errors) == 1 and "Traceback" not in stderr, stderr
    return errors[0]


def resume_in_place(out: Path, data_root: Path, run: Path, *overrides: str,
                    stage: str = "ea") -> dict:
    """``nrt-train ... resume=true`` (:func:`run_train`): it must succeed and continue
    ``run`` in place (no other run folder); returns the run's last checkpoint, loaded."""
    import torch

    proc = run_train(out, data_root, *overrides, "resume=true", stage=stage)
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert sorted(run.parent.iterdir()) == [run]
    return torch.load(run / "checkpoints" / "last.ckpt", weights_only=False, map_location="cpu")


def saved_checkpoint(path: Path, module, hparams: dict | None = None, **extra) -> Path:
    """``module``'s state with ``hparams`` (default: its own) saved as a stage's checkpoint
    is (Lightning's keys, nrt's checkpoint format), without a Trainer; ``extra`` keys are
    added last (and may replace the format)."""
    import lightning
    import torch

    from nrt.stages.checkpoints import stamp

    checkpoint = {"state_dict": module.state_dict(),
                  "hyper_parameters": dict(module.hparams) if hparams is None else hparams,
                  "pytorch-lightning_version": lightning.__version__}
    stamp(checkpoint)
    torch.save({**checkpoint, **extra}, path)
    return path


def single_scene_ea_checkpoint(path: Path) -> Path:
    """A single-scene EA checkpoint at the tiny preset (an EAModule's state and
    hyperparameters, as Lightning writes them), without training one."""
    import hydra

    from nrt.stages.ea import EAModule

    cfg = compose_config("train", ["preset=tiny"])
    module = hydra.utils.instantiate(cfg.model, _convert_="all")
    assert isinstance(module, EAModule)
    return saved_checkpoint(path, module)


def read_csv_metrics(run_dir: Path) -> list[dict]:
    with open(run_dir / "csv" / "metrics.csv") as f:
        return list(csv.DictReader(f))


def values(rows: list[dict], key: str) -> list[float]:
    return [float(r[key]) for r in rows if r.get(key)]


def last_value(rows: list[dict], key: str) -> float:
    return values(rows, key)[-1]


NRT_EVAL = [sys.executable, "-m", "nrt.cli.eval"]


def run_eval(out: Path, data_root: Path, *overrides: str, env: dict | None = None
             ) -> subprocess.CompletedProcess:
    """``nrt-eval preset=tiny`` through the real CLI, writing under ``out``."""
    environ = {**os.environ, "NRT_OUTPUT_DIR": str(out), **(env or {})}
    cmd = [*NRT_EVAL, "preset=tiny", f"paths.data_dir={data_root}", "render.progress=false",
           *overrides]
    return subprocess.run(cmd, env=environ, capture_output=True, text=True, timeout=600)


def eval_metrics(proc: subprocess.CompletedProcess, base: Path) -> tuple[dict, Path]:
    """The metrics of the evaluation ``proc`` ran and its folder: the one folder in
    ``base/eval`` that the command's log names (``base`` is the evaluated run, or the output
    folder for ``grids=``).
    Never "the newest metrics.json anywhere": under ``-n 2`` the other worker evaluates in
    the shared run folders at the same time."""
    assert proc.returncode == 0, proc.stderr[-3000:]
    folders = [p.parent for p in (base / "eval").glob("*/metrics.json")]
    shown = [f for f in folders if str(f) in proc.stdout + proc.stderr]
    assert len(shown) == 1, (folders, proc.stderr[-2000:])
    return json.loads((shown[0] / "metrics.json").read_text())["metrics"], shown[0]


def only_run_dir(out: Path, stage: str) -> Path:
    runs = sorted((out / "default" / stage).iterdir())
    assert len(runs) == 1, runs
    return runs[0]


@pytest.fixture(scope="session")
def tiny_ea_run(tmp_path_factory, tiny_dataset) -> tuple[Path, subprocess.CompletedProcess]:
    """``nrt-train stage=ea preset=tiny`` run once per session via the real CLI: the
    output folder (holding ``default/ea/<run>``) and the finished process. Stage-2 tests
    start from this run's checkpoint."""
    out = session_folder(tmp_path_factory, "tiny_runs")
    record = out / "ea_process.json"
    with building(out):
        if not record.is_file():
            proc = run_train(out, tiny_dataset.parent)
            record.write_text(json.dumps([proc.args, proc.returncode, proc.stdout,
                                          proc.stderr]))
    return out, subprocess.CompletedProcess(*json.loads(record.read_text()))


def computed_by(out: torch.Tensor, node: str) -> bool:
    """Whether ``out``'s autograd graph holds a node whose name starts with ``node`` (the
    fused kernels' ``FusedEncoding``, ``FusedLookup``): which path computed it."""
    todo, seen = [out.grad_fn], set()
    while todo:
        fn = todo.pop()
        if fn is None or fn in seen:
            continue
        seen.add(fn)
        if fn.name().startswith(node):
            return True
        todo += [n for n, _ in fn.next_functions]
    return False


def built_or_skip(extension: LazyExtension):
    """The built C++ extension (built once per machine, then cached), or a skip saying why it
    cannot be built."""
    module = extension.get()
    if module is None:
        pytest.skip(f"{extension.what} cannot be built: {extension.unavailable()}")
    return module


def without_compiler(monkeypatch, tmp_path: Path, owner) -> None:
    """``owner.EXTENSION`` replaced by an unbuilt copy of itself, and no C++ compiler on the
    PATH (nor ``CXX``): the next use tries to build it and fails."""
    ext = owner.EXTENSION
    monkeypatch.setattr(owner, "EXTENSION", LazyExtension(ext.name, ext.sources, ext.what,
                                                          ext.log))
    monkeypatch.setenv("PATH", str(tmp_path))
    monkeypatch.delenv("CXX", raising=False)
