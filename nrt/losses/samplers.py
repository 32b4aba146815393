"""Samplers of stage 2: collocation points in the box and inflow samples on its faces.

These choose *where the losses look*, not Monte Carlo estimators: any distribution with
full support has the same minimiser, so the mixtures below only steer effort to where it
pays (dense medium, bright parts of the sky) and need no pdf weights.
"""

from __future__ import annotations

import torch

from nrt.physics.envmap import EnvironmentDirectionSampler
from nrt.physics.phase import sample_uniform_sphere


def uniform_box_points(n: int, bbox: torch.Tensor, generator: torch.Generator | None = None
                       ) -> torch.Tensor:
    """``n`` points (n, 3) uniform in the box ``bbox`` (2, 3)."""
    u = torch.rand(n, 3, dtype=bbox.dtype, device=bbox.device, generator=generator)
    return bbox[0] + u * (bbox[1] - bbox[0])


class DensityPointSampler:
    """Points distributed like a density grid (R, R, R) indexed ``[z, y, x]`` on ``bbox``:
    a cell drawn in proportion to its density, then a uniform point inside it."""

    def __init__(self, density: torch.Tensor, bbox: torch.Tensor):
        self.resolution = density.shape[0]
        probs = density.detach().flatten().double().clamp_min(0.0)
        total = probs.sum()
        self.probs = probs / total if total > 0 else torch.full_like(probs, 1 / probs.numel())
        self.bbox = bbox

    def sample(self, n: int, generator: torch.Generator | None = None) -> torch.Tensor:
        r = self.resolution
        cell = torch.multinomial(self.probs, n, replacement=True, generator=generator)
        zyx = torch.stack((cell // (r * r), (cell // r) % r, cell % r), -1)
        u = torch.rand(n, 3, dtype=torch.float64, device=cell.device, generator=generator)
        unit = (zyx.flip(-1).double() + u) / r  # x, y, z in [0, 1]
        bbox = self.bbox.double().to(cell.device)
        return (bbox[0] + unit * (bbox[1] - bbox[0])).to(self.bbox)


def collocation_points(n: int, bbox: torch.Tensor, density: DensityPointSampler | None,
                       density_fraction: float, generator: torch.Generator | None = None
                       ) -> torch.Tensor:
    """``n`` points: ``density_fraction`` of them from ``density``, the rest uniform."""
    n_dense = round(n * density_fraction) if density is not None else 0
    parts = [uniform_box_points(n - n_dense, bbox, generator)]
    if n_dense:
        parts.append(density.sample(n_dense, generator))
    return torch.cat(parts)


def _face_counts(n: int, bbox: torch.Tensor) -> list[int]:
    """Samples per face (x-, x+, y-, y+, z-, z+) in proportion to area, summing to n."""
    ext = (bbox[1] - bbox[0]).double()
    area = torch.stack([ext[(a + 1) % 3] * ext[(a + 2) % 3] for a in range(3)]).repeat_interleave(2)
    exact = n * area / area.sum()
    counts = exact.floor().long()
    counts[torch.argsort(exact - counts, descending=True)[: n - int(counts.sum())]] += 1
    return counts.tolist()


def boundary_samples(n: int, bbox: torch.Tensor, env: EnvironmentDirectionSampler | None,
                     env_fraction: float, generator: torch.Generator | None = None
                     ) -> tuple[torch.Tensor, torch.Tensor]:
    """Points on the box faces (n, 3), stratified over the faces by area, and inflowing
    travel directions ``w`` (n, 3) with ``w . n < 0``.

    A share ``env_fraction`` of the directions follows the environment's radiance (light
    from look direction ``d`` travels along ``-d``); one that does not flow in through its
    face, and all others, are uniform on the inflowing hemisphere.
    """
    dev, dt = bbox.device, bbox.dtype
    counts = _face_counts(n, bbox)
    face = torch.repeat_interleave(torch.arange(6, device=dev), torch.tensor(counts, device=dev))
    axis, side = face // 2, face % 2
    u = torch.rand(n, 3, dtype=dt, device=dev, generator=generator)
    pts = bbox[0] + u * (bbox[1] - bbox[0])
    rows = torch.arange(n, device=dev)
    pts[rows, axis] = bbox[side, axis]
    normal = torch.zeros(n, 3, dtype=dt, device=dev)
    normal[rows, axis] = side.to(dt) * 2 - 1
    xi = torch.rand(n, 2, dtype=dt, device=dev, generator=generator)
    w = sample_uniform_sphere(xi)
    dot = (w * normal).sum(-1, keepdim=True)
    w = torch.where(dot > 0, w - 2 * dot * normal, w)  # mirror into the inflowing hemisphere
    n_env = round(n * env_fraction) if env is not None else 0
    if n_env:
        pick = torch.randperm(n, device=dev, generator=generator)[:n_env]
        w_env = -env.sample(n_env, generator).to(device=dev, dtype=dt)
        inflow = (w_env * normal[pick]).sum(-1) < 0
        w[pick[inflow]] = w_env[inflow]
    return pts, w
