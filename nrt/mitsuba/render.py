"""Rendering loaded Mitsuba scenes from OpenGL cameras, plain or with gradients.

:class:`ViewRenderer` loads a scene description (:func:`nrt.mitsuba.scene.scene_dict`) once
and renders it from many cameras, reusing the compiled kernel. For differentiable rendering
(``prbvolpath``) it also writes arrays into the scene's parameters with gradient tracking and
back-propagates an image loss to them in Dr.Jit (:meth:`ViewRenderer.image_loss`).
"""

from __future__ import annotations

from collections.abc import Mapping

import numpy as np
from torch.profiler import record_function

from nrt.cameras import opengl_to_mitsuba


class ViewRenderer:
    """Renders one loaded scene from many OpenGL cameras, reusing the compiled kernel."""

    def __init__(self, mi, scene_description: dict):
        self.mi = mi
        self.scene = mi.load_dict(scene_description)
        self.params = mi.traverse(self.scene)
        self._key = next(k for k in self.params.keys() if k.endswith("to_world")
                         and k.startswith("sensor"))

    def set_camera(self, c2w: np.ndarray) -> None:
        """Place the sensor at the OpenGL camera-to-world ``c2w`` (4, 4)."""
        self.params[self._key] = self.mi.ScalarTransform4f(opengl_to_mitsuba(c2w).tolist())
        self.params.update()

    def render(self, c2w: np.ndarray, spp: int, seed: int) -> np.ndarray:
        """Linear RGB radiance (H, W, 3) float32 seen by camera ``c2w`` (OpenGL)."""
        self.set_camera(c2w)
        img = self.mi.render(self.scene, spp=int(spp), seed=int(seed))
        return np.asarray(img, dtype=np.float32)[..., :3]

    def medium_keys(self, suffixes: Mapping[str, str]) -> dict[str, str]:
        """The scene parameter of each ``name -> key suffix`` (e.g. ``sigma_t.data``) of the
        medium box's interior."""
        return {name: next(k for k in self.params.keys() if k.endswith(suffix)
                           and "interior" in k) for name, suffix in suffixes.items()}

    def set_parameters(self, values: Mapping[str, np.ndarray], grad: bool = False) -> None:
        """Write arrays into the scene's parameters (``key -> array`` in the key's layout),
        tracking gradients with respect to them when ``grad``."""
        import drjit as dr

        for key, value in values.items():
            tensor = self.mi.TensorXf(np.ascontiguousarray(value))
            if grad:
                dr.enable_grad(tensor)
            self.params[key] = tensor
        self.params.update()

    def image_loss(self, c2w: np.ndarray, ref: np.ndarray, values: Mapping[str, np.ndarray],
                   spp: int, seed: int, kind: str = "l2_log"
                   ) -> tuple[float, dict[str, np.ndarray]]:
        """Differentiable rendering: the scene with parameters ``values`` (``key -> array``,
        :meth:`set_parameters`) seen from camera ``c2w`` (OpenGL) against the photo ``ref``
        (H, W, 3), both linear RGB, ``x = max(img, 0)``: ``l2_log`` ``mean((log(1 + x) -
        log(1 + ref))^2)``, ``l1_log`` the same with absolute values, ``l2_relative``
        ``mean((x - ref)^2 / (x_detached + eps)^2)`` with ``eps`` 1 % of the photo's mean
        (RawNeRF's relative MSE: even weight across a high dynamic range).
        Returns the loss and its gradient with respect to each parameter of ``values``
        (float32, flat; non-finite entries are left for the caller to handle)."""
        import drjit as dr

        # profiler scopes (benchmarks.profile_step); Dr.Jit evaluates lazily, so a kernel
        # may run in a later scope than the one that recorded it
        with record_function("nrt/render"):
            self.set_camera(c2w)
            self.set_parameters(values, grad=True)
            reference = self.mi.TensorXf(np.ascontiguousarray(ref))
            img = dr.maximum(self.mi.render(self.scene, self.params, spp=int(spp),
                                            seed=int(seed)), 0)
        with record_function("nrt/image_loss"):
            if kind == "l2_relative":
                eps = 0.01 * float(np.mean(ref)) + 1e-8
                loss = dr.mean(dr.square(img - reference) / dr.square(dr.detach(img) + eps),
                               axis=None)
            else:
                diff = dr.log(1 + img) - dr.log(1 + reference)
                loss = dr.mean(dr.abs(diff) if kind == "l1_log" else dr.square(diff), axis=None)
        with record_function("nrt/render_backward"):
            dr.backward(loss)
            grads = {key: np.asarray(dr.grad(self.params[key]), np.float32) for key in values}
        with record_function("nrt/image_loss"):
            return float(np.asarray(loss).reshape(-1)[0]), grads
