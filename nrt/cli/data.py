"""``nrt-data``: render (or find in the cache) the dataset of a scene and print its folder.
For a family of scenes (``scene=family``) it renders the members missing from the cache and
prints the family folder (its ``family.json`` lists the members' dataset folders).

Only the folder goes to stdout (``DATA=$(nrt-data scene=X)``); logs go to stderr. The
rendering stack (torch, Mitsuba) is imported inside the task, so that ``--cfg``, ``--help``
and config errors answer at once.
"""

from __future__ import annotations

from omegaconf import DictConfig, OmegaConf

from nrt.cli.common import run_app
from nrt.files import check_name


def render_task(cfg: DictConfig) -> str:
    check_name("scene.name", cfg.scene.name)  # at once, before the rendering stack loads
    from nrt.data.family import ensure_family
    from nrt.data.render import ensure_dataset

    scene = OmegaConf.to_container(cfg.scene, resolve=True)
    ensure = ensure_family if scene.get("family") is not None else ensure_dataset
    folder = ensure(scene, cfg.paths.data_dir, variant=cfg.render.variant,
                    progress=cfg.render.progress)
    print(folder, flush=True)
    return str(folder)


def main() -> None:
    run_app(render_task, "dataset", command="nrt-data")


if __name__ == "__main__":
    main()
