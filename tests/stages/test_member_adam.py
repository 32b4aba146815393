"""MemberAdam against independent references: torch's Adam where every member is drawn,
one torch Adam per member stepped on that member's draws alone where some are not."""

import copy

import pytest
import torch
from torch import nn

from nrt.stages.member_adam import MemberAdam, member_blocks, split_member_groups

pytestmark = pytest.mark.unit

K, F = 4, 3


def params(seed: int = 0) -> tuple[nn.Parameter, nn.Parameter, nn.Parameter]:
    g = torch.Generator().manual_seed(seed)
    codes = nn.Parameter(torch.randn(K, 5, generator=g))  # a row a member
    offsets = nn.Parameter(torch.randn(2, 2, 2, K * F, generator=g))  # a block a member, last
    shared = nn.Parameter(torch.randn(6, generator=g))
    return codes, offsets, shared


def member_groups(codes, offsets, shared, **settings) -> list[dict]:
    return split_member_groups([{"params": [shared, offsets], "lr": 0.05, **settings},
                                {"params": [codes], "lr": 0.02, **settings}],
                               [(codes, K, 0), (offsets, K, -1)])


def gradients(step: int, drawn: list[int]) -> tuple[torch.Tensor, ...]:
    """Random gradients of step ``step`` that are zero outside the ``drawn`` members."""
    g = torch.Generator().manual_seed(100 + step)
    codes, offsets, shared = (torch.randn(K, 5, generator=g),
                              torch.randn(2, 2, 2, K * F, generator=g), torch.randn(6, generator=g))
    mask = torch.zeros(K, dtype=torch.bool)
    mask[drawn] = True
    codes = codes * mask[:, None]
    offsets = offsets * mask.repeat_interleave(F)
    return codes, offsets, shared


def test_member_blocks_views_each_members_block():
    t = torch.arange(2 * K * F).reshape(2, K * F)
    blocks = member_blocks(t, K, -1)
    assert blocks.shape == (K, 2, F)
    assert torch.equal(blocks[1], t[:, F:2 * F])
    blocks[2] += 1000  # a view: writing a block writes the tensor
    assert (t[:, 2 * F:3 * F] >= 1000).all() and (t[:, :2 * F] < 1000).all()
    with pytest.raises(ValueError, match="equal members"):
        member_blocks(torch.zeros(2, 7), K, -1)


def test_split_member_groups_keeps_each_groups_settings():
    codes, offsets, shared = params()
    groups = member_groups(codes, offsets, shared, ramps_in=True)
    assert [len(g["params"]) for g in groups] == [1, 1, 1]
    assert groups[0]["params"][0] is shared and "members" not in groups[0]
    assert groups[1]["params"][0] is offsets and groups[1]["member_axis"] == -1
    assert groups[2]["params"][0] is codes and groups[2]["member_axis"] == 0
    assert all(g["ramps_in"] for g in groups)
    assert [g["lr"] for g in groups] == [0.05, 0.05, 0.02]


@pytest.mark.parametrize("weight_decay", [0.0, 0.1])
def test_every_member_drawn_is_torch_adam(weight_decay):
    """Where every member is drawn every step, each block's own step count is the global
    one: MemberAdam is torch's Adam (to float rounding: the update is computed per block)."""
    ours, ref = params(), params()
    opt = MemberAdam(member_groups(*ours, weight_decay=weight_decay))
    ref_opt = torch.optim.Adam([{"params": [ref[2], ref[1]], "lr": 0.05},
                                {"params": [ref[0]], "lr": 0.02}], weight_decay=weight_decay)
    for step in range(30):
        for group in (ours, ref):
            for p, grad in zip(group, gradients(step, list(range(K))), strict=True):
                p.grad = grad.clone()
        opt.step()
        ref_opt.step()
    for a, b in zip(ours, ref, strict=True):
        torch.testing.assert_close(a, b, rtol=1e-5, atol=1e-6)


def test_an_undrawn_member_stays_and_a_drawn_one_follows_its_own_adam():
    """Members drawn on some steps: a block whose gradient is zero keeps its value and its
    moments; each block ends where a torch Adam of its own, stepped on its member's draws
    only, ends; the shared parameter follows plain Adam over every step."""
    codes, offsets, shared = params()
    start = [p.detach().clone() for p in (codes, offsets, shared)]
    opt = MemberAdam(member_groups(codes, offsets, shared))
    own = [[nn.Parameter(member_blocks(start[i], K, axis)[k].clone()) for k in range(K)]
           for i, axis in ((0, 0), (1, -1))]
    own_opts = [[torch.optim.Adam([p], lr=lr) for p in blocks]
                for blocks, lr in zip(own, (0.02, 0.05), strict=True)]
    ref_shared = nn.Parameter(start[2].clone())
    ref_shared_opt = torch.optim.Adam([ref_shared], lr=0.05)
    draws = [[0, 1], [2, 3], [0, 2], [1, 0], [3, 0], [2, 1]] * 4 + [[0, 1]] * 5
    for step, drawn in enumerate(draws):
        grads = gradients(step, drawn)
        codes.grad, offsets.grad, shared.grad = (g.clone() for g in grads)
        before = offsets.detach().clone()
        opt.step()
        for k in set(range(K)) - set(drawn):  # undrawn: unchanged
            assert torch.equal(member_blocks(offsets.detach(), K, -1)[k],
                               member_blocks(before, K, -1)[k])
        for i, axis in ((0, 0), (1, -1)):
            for k in drawn:
                own[i][k].grad = member_blocks(grads[i], K, axis)[k].clone()
                own_opts[i][k].step()
        ref_shared.grad = grads[2].clone()
        ref_shared_opt.step()
    for i, (p, axis) in enumerate(((codes, 0), (offsets, -1))):
        for k in range(K):
            torch.testing.assert_close(member_blocks(p.detach(), K, axis)[k], own[i][k].detach(),
                                       rtol=1e-5, atol=1e-6)
    torch.testing.assert_close(shared.detach(), ref_shared.detach(), rtol=1e-6, atol=1e-7)
    assert opt.state[offsets]["step"].tolist() == [
        sum(k in d for d in draws) for k in range(K)]


def test_a_saved_state_resumes_exactly():
    """A killed run resumes: the state dict (the per-member step counts included) restores
    the same steps."""
    first, second = params(), params()
    opt = MemberAdam(member_groups(*first))
    draws = [[0, 1], [2, 3], [1, 3]] * 3
    for step, drawn in enumerate(draws[:5]):
        for p, grad in zip(first, gradients(step, drawn), strict=True):
            p.grad = grad.clone()
        opt.step()
    with torch.no_grad():
        for a, b in zip(second, first, strict=True):
            a.copy_(b)
    resumed = MemberAdam(member_groups(*second))
    resumed.load_state_dict(copy.deepcopy(opt.state_dict()))  # as from a checkpoint
    for step, drawn in enumerate(draws[5:], start=5):
        for group, o in ((first, opt), (second, resumed)):
            for p, grad in zip(group, gradients(step, drawn), strict=True):
                p.grad = grad.clone()
            o.step()
    for a, b in zip(first, second, strict=True):
        assert torch.equal(a, b)


def test_refuses_amsgrad_in_a_member_group():
    codes, offsets, shared = params()
    with pytest.raises(ValueError, match="amsgrad"):
        MemberAdam(member_groups(codes, offsets, shared), amsgrad=True)
