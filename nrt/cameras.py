"""Pinhole cameras in the NeRF-synthetic / nerfstudio convention.

``c2w`` is a camera-to-world 4x4 matrix of an OpenGL camera: it looks down its local -Z,
+Y is up and +X is right in the image. Pixel ``(row, col)`` spans ``[col, col + 1) x
[row, row + 1)`` in image coordinates; its centre is at ``+0.5``. A pixel's view direction
``v`` points from the camera into the scene, and the pixel value is the radiance arriving
at the camera, ``I = L(o, -v)``. Mitsuba's cameras look down +Z with +X to the left;
:func:`opengl_to_mitsuba` converts, and a test renders a known point to pin it.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch

from nrt.errors import NrtError


@dataclass(frozen=True)
class Intrinsics:
    """Pinhole intrinsics in pixels (``fx = fy`` for square pixels)."""

    width: int
    height: int
    fx: float
    fy: float
    cx: float
    cy: float

    @classmethod
    def from_fov_x(cls, width: int, height: int, camera_angle_x: float) -> Intrinsics:
        """Square pixels and a centred principal point from the horizontal FOV (radians)."""
        f = 0.5 * width / math.tan(0.5 * camera_angle_x)
        return cls(width, height, f, f, 0.5 * width, 0.5 * height)

    @property
    def camera_angle_x(self) -> float:
        return 2 * math.atan(0.5 * self.width / self.fx)


def fov_x_deg(intr: Intrinsics, source: str = "The cameras") -> float:
    """Horizontal field of view (degrees) of a pinhole camera for Mitsuba's
    ``perspective`` sensor, which needs a centred principal point and square pixels;
    ``source`` names the cameras in the error otherwise."""
    if abs(intr.cx - intr.width / 2) > 1e-3 * intr.width or \
            abs(intr.cy - intr.height / 2) > 1e-3 * intr.height or \
            abs(intr.fx - intr.fy) > 1e-3 * intr.fx:
        raise NrtError(f"{source}: rendering with Mitsuba needs square pixels and a centred "
                       "principal point (cx = w/2, cy = h/2, fl_x = fl_y); these cameras have "
                       f"fl=({intr.fx}, {intr.fy}), c=({intr.cx}, {intr.cy}).")
    return math.degrees(intr.camera_angle_x)


def camera_rays(c2w: torch.Tensor, intr: Intrinsics, x: torch.Tensor, y: torch.Tensor
                ) -> tuple[torch.Tensor, torch.Tensor]:
    """Origins and unit view directions (..., 3) through image points ``(x, y)`` (...).

    ``x`` runs right along a row and ``y`` down a column, in pixels (pixel centres at
    ``+0.5``); ``c2w`` is (4, 4) or broadcasts as (..., 4, 4).
    """
    d_cam = torch.stack(
        ((x - intr.cx) / intr.fx, -(y - intr.cy) / intr.fy, -torch.ones_like(x)), -1
    )
    d = (c2w[..., :3, :3] @ d_cam.unsqueeze(-1)).squeeze(-1)
    d = d / d.norm(dim=-1, keepdim=True)
    return c2w[..., :3, 3].expand_as(d), d


def pixel_rays(
    c2w: torch.Tensor, intr: Intrinsics, offsets: torch.Tensor | None = None
) -> tuple[torch.Tensor, torch.Tensor]:
    """World-space origins and unit view directions ``v`` of every pixel, (H, W, 3) each.

    ``offsets`` (H, W, 2) or (2,) in [0, 1) places the ray inside its pixel (x, y); the
    default 0.5 is the pixel centre. Jittered training rays pass uniform offsets.
    """
    dtype, device = c2w.dtype, c2w.device
    rows = torch.arange(intr.height, dtype=dtype, device=device)
    cols = torch.arange(intr.width, dtype=dtype, device=device)
    y, x = torch.meshgrid(rows, cols, indexing="ij")
    if offsets is None:
        offsets = torch.tensor([0.5, 0.5], dtype=dtype, device=device)
    return camera_rays(c2w, intr, x + offsets[..., 0], y + offsets[..., 1])


def look_at(eye: np.ndarray, target: np.ndarray, up: np.ndarray | None = None) -> np.ndarray:
    """OpenGL camera-to-world matrix at ``eye`` looking at ``target`` (4x4, float64)."""
    eye, target = np.asarray(eye, float), np.asarray(target, float)
    forward = target - eye
    forward /= np.linalg.norm(forward)
    up = np.array([0.0, 1.0, 0.0]) if up is None else np.asarray(up, float)
    if abs(float(forward @ up)) > 0.999:  # looking straight up or down: any other up works
        up = np.array([0.0, 0.0, 1.0])
    right = np.cross(forward, up)
    right /= np.linalg.norm(right)
    true_up = np.cross(right, forward)
    c2w = np.eye(4)
    c2w[:3, 0], c2w[:3, 1], c2w[:3, 2], c2w[:3, 3] = right, true_up, -forward, eye
    return c2w


def opengl_to_mitsuba(c2w: np.ndarray) -> np.ndarray:
    """Mitsuba sensor ``to_world`` for an OpenGL ``c2w`` (flip the local X and Z axes)."""
    return np.asarray(c2w, float) @ np.diag([-1.0, 1.0, -1.0, 1.0])


def sphere_positions(n: int, radius: float, seed: int) -> np.ndarray:
    """``n`` well-spread points on a sphere (Fibonacci lattice under a random rotation)."""
    i = np.arange(n) + 0.5
    y = 1 - 2 * i / n
    r = np.sqrt(1 - y * y)
    phi = math.pi * (3 - math.sqrt(5)) * i
    pts = np.stack((r * np.cos(phi), y, r * np.sin(phi)), -1)
    q, _ = np.linalg.qr(np.random.default_rng(seed).normal(size=(3, 3)))
    return radius * pts @ q.T
