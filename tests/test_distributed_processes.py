"""nrt/distributed.py's collectives in two real processes (gloo on the CPU): the ranks start
from rank 0's parameters and buffers, and each gradient becomes its mean over the ranks,
a missing one counting zero and one missing everywhere staying missing."""

from __future__ import annotations

import socket
from pathlib import Path

import pytest
import torch
import torch.distributed as dist
import torch.multiprocessing as mp

from nrt.distributed import average_gradients, broadcast_state

pytestmark = pytest.mark.integration


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _rank(rank: int, world: int, port: int, out: str) -> None:
    """One rank: a module built from its own seed, then set to rank 0's; gradients that
    differ by rank (``a``), that no rank has (``b``), that rank 1 alone has (``c``, of the
    shape a grid has after doubling), averaged."""
    dist.init_process_group("gloo", init_method=f"tcp://127.0.0.1:{port}", rank=rank,
                            world_size=world)
    try:
        torch.manual_seed(rank)
        module = torch.nn.Linear(3, 2)
        module.register_buffer("flags", torch.tensor([rank == 0, rank == 1]))
        broadcast_state(module)
        a = torch.nn.Parameter(torch.zeros(2, 2))
        b = torch.nn.Parameter(torch.zeros(3))
        c = torch.nn.Parameter(torch.zeros(4, 4, 4, 1))
        a.grad = torch.full((2, 2), float(rank + 1))
        if rank == 1:
            c.grad = torch.full((4, 4, 4, 1), 4.0)
        average_gradients([a, b, c, a])  # a parameter twice counts once
        torch.save({"state": module.state_dict(), "a": a.grad, "b": b.grad, "c": c.grad},
                   Path(out) / f"rank{rank}.pt")
    finally:
        dist.destroy_process_group()


@pytest.mark.slow  # 9 s: two processes started and joined
def test_ranks_start_alike_and_average_their_gradients(tmp_path):
    mp.spawn(_rank, args=(2, _free_port(), str(tmp_path)), nprocs=2)
    ranks = [torch.load(tmp_path / f"rank{r}.pt", weights_only=True) for r in range(2)]
    torch.manual_seed(0)
    expected = torch.nn.Linear(3, 2)
    for saved in ranks:
        torch.testing.assert_close(saved["state"]["weight"], expected.weight.detach(),
                                   rtol=0, atol=0)
        assert saved["state"]["flags"].tolist() == [True, False]  # rank 0's buffer
        assert torch.equal(saved["a"], torch.full((2, 2), 1.5))
        assert saved["b"] is None
        assert torch.equal(saved["c"], torch.full((4, 4, 4, 1), 2.0))
