"""How fast the machine is at a moment: a float32 matrix product and a streaming add, each
repeated for a fixed time. ``benchmarks.profile_step`` sets a step's FLOPs and bytes against
them; equal-time records (``benchmarks.equal_time``) carry them, so runs made hours apart on a
shared machine can be checked for a change of speed between them.
"""

from __future__ import annotations

import os
import platform
import time

import torch

DEFAULT_GEMM = (8192, 64, 64)
"""The GEMM probe's (M, K, N) for a step whose matrix products hold under 10 % of its FLOPs
(stage 2's default, dpt): an MLP layer of 64 units over 8192 points."""


def gemm_probe(shape: tuple[int, int, int], seconds: float) -> float:
    """GFLOP/s of a float32 ``(M, K) @ (K, N)`` product repeated for ``seconds``."""
    m, k, n = shape
    a, b, c = torch.randn(m, k), torch.randn(k, n), torch.empty(m, n)
    torch.mm(a, b, out=c)
    calls, start = 0, time.perf_counter()
    while (elapsed := time.perf_counter() - start) < seconds or calls == 0:
        for _ in range(10):
            torch.mm(a, b, out=c)
        calls += 10
    return 2.0 * m * k * n * calls / elapsed / 1e9


def bandwidth_probe(seconds: float, numel: int = 2**25) -> float:
    """GB/s of ``c = a + b`` over float32 tensors of ``numel`` elements (128 MiB each),
    counting the bytes read and written, repeated for ``seconds``."""
    a, b, c = torch.rand(numel), torch.rand(numel), torch.empty(numel)
    torch.add(a, b, out=c)
    calls, start = 0, time.perf_counter()
    while (elapsed := time.perf_counter() - start) < seconds or calls == 0:
        torch.add(a, b, out=c)
        calls += 1
    return 3.0 * 4 * numel * calls / elapsed / 1e9


def machine_speed(seconds: float = 1.0) -> dict:
    """The machine now: the GEMM probe at :data:`DEFAULT_GEMM` and the bandwidth probe,
    ``seconds`` each, with the host's name, processor, cores and torch's threads."""
    return {"host": platform.node(), "processor": platform.processor() or platform.machine(),
            "cores": os.cpu_count(), "torch_threads": torch.get_num_threads(),
            "gemm_gflops": round(gemm_probe(DEFAULT_GEMM, seconds), 2),
            "bandwidth_gbs": round(bandwidth_probe(seconds), 2)}
