"""What the two stage-2 test modules (the paper's formulation and the split default) share:
the hard cases that must train without NaN or Inf, the scenes with and without direct light,
and spies on the functions and objectives a step calls."""

from __future__ import annotations

import numpy as np
import torch

from nrt.data.exr import write_exr
from tests.finite_training import fit


def bright_sun_sky(path) -> str:
    """A 32 x 64 sky of radiance 0.5 with a sun 1e4 times brighter (3 x 3 texels)."""
    sky = np.full((32, 64, 3), 0.5, np.float32)
    sky[8:11, 20:23] = 5e3
    write_exr(path, sky)
    return str(path)


HARD_CASES = {
    "dense": ["scene.medium.max_extinction=50"],
    "forward_g": ["scene.medium.g=0.95"],
    "backward_g": ["scene.medium.g=-0.95"],
    "near_empty": ["scene.medium.max_extinction=1e-4"],
    "grazing_cameras": ["scene.cameras.radius=1.75", "scene.cameras.fov_x_deg=90"],
    "point_light": ["scene.effects.emitters=[{position:[0.0,0.0,0.0],"
                    "intensity:[1000.0,1000.0,1000.0]}]"],
}


def hard_case_overrides(case: str, tmp_path) -> list[str]:
    """A hard case's scene overrides (``sun_1e4``: a sun 1e4 times its sky, as an EXR)."""
    return HARD_CASES.get(case) or [
        "scene.environments.sky_seeds=[]",
        f"+scene.environments.files.sun={bright_sun_sky(tmp_path / 'sun.exr')}"]


def trains_finite(model, dm, steps: int) -> None:
    """``steps`` steps run, and the medium's grids and the predicted pixels stay finite."""
    trainer = fit(model, dm, steps)
    assert trainer.global_step == steps
    grids = model.medium.grids(8)
    assert all(torch.isfinite(v).all() for v in grids.values())
    batch = next(iter(dm.val_dataloader()))
    pred = model.predict_pixels(batch["origins"], batch["dirs"], batch["background"])
    assert all(torch.isfinite(p).all() for p in pred.values())


def count_calls(monkeypatch, module, name: str) -> list:
    calls: list = []
    original = getattr(module, name)

    def spy(*args, **kwargs):
        calls.append(1)
        return original(*args, **kwargs)

    monkeypatch.setattr(module, name, spy)
    return calls


def spy_objectives(monkeypatch, model) -> list[tuple[int, str]]:
    """(step, name) of every loss the model's objectives compute from now on."""
    called: list[tuple[int, str]] = []
    for name, unit in model.objectives.items():
        def spy(batch, context, name=name, original=unit.loss):
            called.append((model.global_step, name))
            return original(batch, context)
        monkeypatch.setattr(unit, "loss", spy)
    return called


DIRECT_LIGHT_CASES = [  # (model.sun.threshold, scene.effects.emitters, direct light built)
    ("null", "[]", False),
    ("10.0", "[]", True),
    ("null", "[{position:[0.0,2.0,0.0],intensity:[5.0,5.0,5.0]}]", True),
]
