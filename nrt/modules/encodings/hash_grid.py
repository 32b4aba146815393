"""Multiresolution hash encoding (instant-ngp) in pure PyTorch; runs on CPU and CUDA.

Level ``l`` has resolution ``N_l = floor(base_resolution * growth**l)`` cells per axis over
the unit cube and ``(N_l + 1)^3`` vertices. A level whose vertices fit the table is indexed
densely (``x + y (N+1) + z (N+1)^2``); finer levels hash the vertex with tiny-cuda-nn's
primes ``(1, 2654435761, 805459861)``: ``(x * p0 ^ y * p1 ^ z * p2) mod T``. Features are
trilinearly interpolated and concatenated over levels. The tables are one flat parameter
gathered with ``index_select`` (its backward is ``index_add_``, far faster on CPU than an
embedding's dense backward, docs/conventions.md, "Runtime").

``fused=True`` computes the same on CPU with fused C++ kernels where no gradient with respect
to the points is needed (:mod:`nrt.modules.encodings.fused_hash_grid`).
"""

from __future__ import annotations

import math

import torch
from torch import nn
from torch.profiler import record_function

from nrt.modules.encodings import fused_hash_grid

PRIMES = (1, 2654435761, 805459861)

_CORNERS = torch.tensor([[i, j, k] for k in (0, 1) for j in (0, 1) for i in (0, 1)])


class HashGrid(nn.Module):
    """Encode points in [0, 1]^3 (..., 3) into features (..., levels * features); ``fused``:
    with the fused CPU kernels where they apply (:func:`fused_hash_grid.fusable`)."""

    def __init__(self, levels: int = 16, features: int = 2, log2_table_size: int = 19,
                 base_resolution: int = 16, growth: float = 1.5, init_scale: float = 1e-4,
                 fused: bool = False):
        super().__init__()
        self.levels, self.features, self.fused = levels, features, bool(fused)
        self.table_size = 2**log2_table_size
        self.resolutions = [int(math.floor(base_resolution * growth**lv)) for lv in range(levels)]
        self.dense = [(r + 1) ** 3 <= self.table_size for r in self.resolutions]
        sizes = [(r + 1) ** 3 if d else self.table_size
                 for r, d in zip(self.resolutions, self.dense, strict=True)]
        offsets = torch.tensor([0] + sizes).cumsum(0)
        self.register_buffer("offsets", offsets[:-1], persistent=False)
        self.fused_levels = (self.resolutions, offsets[:-1].tolist(), self.dense,
                             self.table_size)  # the fused kernels' arguments
        self.table = nn.Parameter(
            torch.empty(int(offsets[-1]), features).uniform_(-init_scale, init_scale))
        self.register_buffer("corners", _CORNERS.clone(), persistent=False)

    @property
    def output_dim(self) -> int:
        return self.levels * self.features

    def vertex_index(self, level: int, vertex: torch.Tensor) -> torch.Tensor:
        """Row in the flat table of integer vertices (..., 3) of ``level``."""
        vertex = vertex.long()
        if self.dense[level]:
            n = self.resolutions[level] + 1
            idx = vertex[..., 0] + n * (vertex[..., 1] + n * vertex[..., 2])
        else:
            idx = (vertex[..., 0] * PRIMES[0]) ^ (vertex[..., 1] * PRIMES[1]) ^ (
                vertex[..., 2] * PRIMES[2])
            idx = idx & (self.table_size - 1)  # T is a power of two: same as uint32 wrap mod T
        return idx + self.offsets[level]

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        with record_function("nrt/hash_grid"):  # a profiler scope (benchmarks.profile_step)
            lead = x.shape[:-1]
            if self.fused and fused_hash_grid.fusable(x, self.table):
                out = fused_hash_grid.fused_encode(x.reshape(-1, 3), self.table,
                                                   self.fused_levels)
                if out is not None:
                    return out.reshape(*lead, self.output_dim)
            x = x.reshape(-1, 3).clamp(0.0, 1.0)
            out = []
            for level, res in enumerate(self.resolutions):
                pos = x * res
                base = torch.floor(pos).clamp(max=res - 1)
                frac = pos - base  # (P, 3)
                vertices = base.long().unsqueeze(1) + self.corners  # (P, 8, 3)
                rows = self.vertex_index(level, vertices)  # (P, 8)
                feats = torch.index_select(self.table, 0, rows.reshape(-1)).view(
                    -1, 8, self.features)
                w = torch.where(self.corners.bool(), frac.unsqueeze(1),
                                1 - frac.unsqueeze(1)).prod(-1)
                out.append((feats * w.unsqueeze(-1)).sum(1))
            return torch.cat(out, -1).reshape(*lead, self.output_dim)
