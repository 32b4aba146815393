"""The non-finite guard (:class:`nrt.callbacks.NonFiniteGuard`): non-finite gradient entries
are zeroed and counted, finite ones are left bit for bit, a parameter that turns non-finite
stops training naming it, and the one-sum test (:func:`nrt.callbacks.all_finite`) gives the
entry-by-entry answer, also where a sum of finite values overflows."""

from __future__ import annotations

from types import SimpleNamespace

import pytest
import torch

from nrt.callbacks import NonFiniteGuard, all_finite

pytestmark = pytest.mark.unit


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_one_sum_decides_as_the_entries_do(dtype):
    big = torch.finfo(dtype).max
    cases = [torch.randn(1000, dtype=dtype), torch.full((4,), big, dtype=dtype),  # overflows
             torch.tensor([1.0, float("nan")], dtype=dtype),
             torch.tensor([float("inf"), -float("inf")], dtype=dtype),  # sums to NaN
             torch.tensor([float("inf"), 1.0], dtype=dtype), torch.zeros(0, dtype=dtype)]
    assert [all_finite(t) for t in cases] == [bool(torch.isfinite(t).all()) for t in cases]
    assert all_finite(cases[1])  # finite entries whose sum is infinite


class Module(torch.nn.Module):
    """Two parameters and the ``log`` a LightningModule has."""

    def __init__(self):
        super().__init__()
        self.a, self.b = torch.nn.Parameter(torch.ones(6)), torch.nn.Parameter(torch.ones(3))
        self.logged = {}

    def log(self, key, value):
        self.logged[key] = value


def test_nonfinite_gradient_entries_are_zeroed_and_counted():
    module, guard = Module(), NonFiniteGuard()
    module.a.grad = torch.tensor([1.0, float("nan"), float("inf"), 2.0, -float("inf"), 3.0])
    finite = torch.tensor([3e38, 3e38, -5.0])  # sums past float32's range, all finite
    module.b.grad = finite.clone()
    guard.on_before_optimizer_step(SimpleNamespace(global_step=7), module, None)
    assert torch.equal(module.a.grad, torch.tensor([1.0, 0.0, 0.0, 2.0, 0.0, 3.0]))
    assert torch.equal(module.b.grad, finite) and module.logged["guard/nonfinite_grads"] == 3.0


def test_a_parameter_that_turns_nonfinite_stops_training_naming_it():
    module, guard = Module(), NonFiniteGuard()
    guard.on_train_batch_end(SimpleNamespace(global_step=3), module, None, None, 0)
    with torch.no_grad():
        module.b[1] = float("nan")
    with pytest.raises(FloatingPointError, match="'b' became non-finite at step 3"):
        guard.on_train_batch_end(SimpleNamespace(global_step=3), module, None, None, 0)
