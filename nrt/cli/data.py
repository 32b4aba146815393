"""``nrt-data``: render (or find in the cache) the dataset of a scene and print its folder."""

from __future__ import annotations

from omegaconf import DictConfig, OmegaConf

from nrt.cli.common import run_app
from nrt.data.render import ensure_dataset


def render_task(cfg: DictConfig) -> str:
    scene = OmegaConf.to_container(cfg.scene, resolve=True)
    folder = ensure_dataset(scene, cfg.paths.data_dir, variant=cfg.render.variant,
                            progress=cfg.render.progress)
    print(folder)
    return str(folder)


def main() -> None:
    run_app(render_task, "data")


if __name__ == "__main__":
    main()
