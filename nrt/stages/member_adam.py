"""Adam that steps each family member's own parameters only on the steps that draw it.

A family's codes (K, d_z) and its members' feature offsets (..., K * F) hold one block per
member in one tensor. With ``data.members_per_step`` M < K a step's photos reach M blocks;
the others get a zero gradient, and plain Adam still moves them: their first moment decays
over the next ~1 / (1 - beta1) steps while the second moment averages in the zeros, so each
gradient a member receives moves it by about sqrt(K / M) learning rates, spread over the
steps that follow, where a single scene's parameter moves by about one a step.

:class:`MemberAdam` is Adam for every group without a ``members`` key; a group with
``members`` (K) and ``member_axis`` (the axis of its tensors that holds the K equal blocks)
gets lazy Adam per block: a block whose gradient is zero everywhere this step is left as it
is, moments included, and each block counts its own steps for the bias correction (the
state's ``step``: one count a member, float64). Each member's parameters then follow the
Adam of a single scene trained on the steps that drew it. Weight decay, where a group sets
it, is added to the gradient of the stepped blocks (Adam's L2 form); ``amsgrad``,
``maximize`` and complex parameters are refused in those groups.
"""

from __future__ import annotations

import torch
from torch import nn


def member_blocks(tensor: torch.Tensor, members: int, axis: int) -> torch.Tensor:
    """A view (K, ...) of ``tensor`` whose leading index is the member: ``axis`` holds
    ``members`` equal blocks, one a member."""
    a = axis % tensor.dim()
    if tensor.shape[a] % members:
        raise ValueError(f"axis {axis} of a tensor of shape {tuple(tensor.shape)} does not "
                         f"split into {members} equal members' blocks.")
    return tensor.unflatten(a, (members, -1)).movedim(a, 0)


def split_member_groups(groups: list[dict],
                        blocks: list[tuple[nn.Parameter, int, int]]) -> list[dict]:
    """``groups`` with each parameter of ``blocks`` ((parameter, members, member axis))
    moved out of its group into a group of its own, with the group's other settings and
    the ``members`` and ``member_axis`` that :class:`MemberAdam` reads. A parameter of
    ``blocks`` in no group is not trained, and none is added."""
    layout = {id(p): (members, axis) for p, members, axis in blocks}
    out = []
    for group in groups:
        params = list(group["params"])
        shared = [p for p in params if id(p) not in layout]
        settings = {k: v for k, v in group.items() if k != "params"}
        if shared:
            out.append({**settings, "params": shared})
        for p in params:
            if id(p) in layout:
                members, axis = layout[id(p)]
                out.append({**settings, "params": [p], "members": members, "member_axis": axis})
    return out


class MemberAdam(torch.optim.Adam):
    """:class:`torch.optim.Adam`, with lazy Adam per member's block in the groups that carry
    ``members`` and ``member_axis`` (:func:`split_member_groups`)."""

    def __init__(self, params, **kwargs):
        super().__init__(params, **kwargs)
        for group in self.param_groups:
            if "members" in group and (group["amsgrad"] or group["maximize"]
                                       or any(p.is_complex() for p in group["params"])):
                raise ValueError("MemberAdam steps members' blocks without amsgrad, maximize "
                                 "or complex parameters.")

    @torch.no_grad()
    def step(self, closure=None):
        loss = None
        if closure is not None:
            with torch.enable_grad():
                loss = closure()
        member_params = [p for g in self.param_groups if "members" in g for p in g["params"]]
        grads = [p.grad for p in member_params]
        for p in member_params:  # plain Adam skips a parameter without a gradient
            p.grad = None
        try:
            super().step()
        finally:
            for p, grad in zip(member_params, grads, strict=True):
                p.grad = grad
        for group in self.param_groups:
            if "members" in group:
                for p in group["params"]:
                    if p.grad is not None:
                        self._member_step(p, group)
        return loss

    def _member_step(self, p: nn.Parameter, group: dict) -> None:
        members, axis = group["members"], group["member_axis"]
        beta1, beta2 = group["betas"]
        state = self.state[p]
        if not state:
            state["step"] = torch.zeros(members, dtype=torch.float64, device=p.device)
            state["exp_avg"] = torch.zeros_like(p, memory_format=torch.preserve_format)
            state["exp_avg_sq"] = torch.zeros_like(p, memory_format=torch.preserve_format)
        grad = member_blocks(p.grad, members, axis)
        drawn = grad.flatten(1).abs().amax(1) > 0
        if not drawn.any():
            return
        value = member_blocks(p, members, axis)
        g = grad[drawn]
        if group["weight_decay"]:
            g = g + group["weight_decay"] * value[drawn]
        steps = state["step"]
        steps[drawn] += 1
        m = member_blocks(state["exp_avg"], members, axis)
        v = member_blocks(state["exp_avg_sq"], members, axis)
        m_new = m[drawn].mul_(beta1).add_(g, alpha=1 - beta1)
        v_new = v[drawn].mul_(beta2).addcmul_(g, g, value=1 - beta2)
        m[drawn], v[drawn] = m_new, v_new
        shape = (-1,) + (1,) * (g.dim() - 1)
        n = steps[drawn].reshape(shape)  # float64: 1 - beta2^n cancels in float32
        step_size = (group["lr"] / (1 - beta1 ** n)).to(p.dtype)
        bias2_sqrt = (1 - beta2 ** n).sqrt().to(p.dtype)
        denom = (v_new.sqrt() / bias2_sqrt).add_(group["eps"])
        value[drawn] = value[drawn] - step_size * m_new / denom
