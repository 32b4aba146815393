"""Helpers shared by the benchmarks: compose nrt's real configs outside a Hydra app."""

from __future__ import annotations

from hydra import compose, initialize_config_dir
from omegaconf import DictConfig

from nrt.cli.common import CONFIG_DIR, register_resolvers


def compose_train(overrides: list[str]) -> DictConfig:
    """The ``nrt-train`` config with ``overrides``, as the CLI would compose it."""
    register_resolvers()
    with initialize_config_dir(config_dir=str(CONFIG_DIR), version_base="1.3"):
        return compose("train", overrides=overrides)
