"""Shared fixtures: configs composed from the real conf/ tree, and the ``tiny`` dataset of
the default scene, rendered once per test session and reused by every test that reads it."""

from __future__ import annotations

import os

# As the nrt commands do (nrt.cli.common.run_app): idle OpenMP threads sleep instead of
# spinning, so tests and the subprocesses they start do not starve each other.
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

import copy
from collections.abc import Callable
from pathlib import Path

import pytest
from hydra import compose, initialize_config_dir
from omegaconf import DictConfig, OmegaConf

from nrt.cli.common import CONFIG_DIR, register_resolvers
from nrt.data.render import ensure_dataset


def compose_config(config_name: str = "data", overrides: list[str] | tuple = ()) -> DictConfig:
    """``conf/<config_name>.yaml`` with ``overrides``, composed as the CLI composes it."""
    register_resolvers()
    with initialize_config_dir(config_dir=str(CONFIG_DIR), version_base="1.3"):
        return compose(config_name, overrides=list(overrides))


_scenes: dict[tuple[str, ...], dict] = {}


@pytest.fixture
def scene_config() -> Callable[..., dict]:
    """Factory: the resolved ``scene`` group (a fresh plain dict) of ``preset=tiny`` and
    ``overrides``. Compositions are cached per session (Hydra takes ~0.15 s each)."""

    def make(*overrides: str) -> dict:
        if overrides not in _scenes:
            cfg = compose_config("data", ["preset=tiny", *overrides])
            _scenes[overrides] = OmegaConf.to_container(cfg.scene, resolve=True)
        return copy.deepcopy(_scenes[overrides])

    return make


@pytest.fixture(scope="session")
def tiny_output_dir(tmp_path_factory) -> Path:
    """``paths.output_dir`` of the session's tiny dataset (datasets live in ``datasets/``)."""
    return tmp_path_factory.mktemp("nrt_output")


@pytest.fixture(scope="session")
def tiny_dataset(tiny_output_dir) -> Path:
    """Folder of the default scene's ``tiny`` dataset (16 train + 4 test views of 32x32
    under one sky), rendered with Mitsuba once per session. Treat it as read-only: tests
    that corrupt a dataset copy it first."""
    cfg = compose_config("data", ["preset=tiny", f"paths.output_dir={tiny_output_dir}"])
    scene = OmegaConf.to_container(cfg.scene, resolve=True)
    folder = ensure_dataset(scene, cfg.paths.data_dir, progress=False)
    assert (folder / "scene.json").is_file(), folder
    return folder
