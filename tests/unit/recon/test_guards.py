"""The step guards of both stages (fgat.recon.guards): non-finite loss terms and
gradients are named, finite ones pass, and a guarded step reads the host once; the stages' Adam
(fgat._core.devices.adam) takes PyTorch's reference update and reads nothing back."""

import math

import pytest
import torch

from fgat._core.devices import DispatchCount, adam
from fgat.recon import guards
from fgat.recon.guards import check_step, descend


def test_loss_terms_come_back_as_floats_and_the_first_non_finite_one_is_named():
    terms = {
        "total": torch.tensor(0.25, dtype=torch.float32),
        "pix": torch.tensor(0.2, dtype=torch.float32),
        "l1": torch.tensor(0.05, dtype=torch.float64),
    }
    assert check_step(terms, [], "step 3", 3) == {name: float(v) for name, v in terms.items()}
    for value, shown in ((math.nan, "nan"), (math.inf, "inf"), (-math.inf, "-inf")):
        broken = {**terms, "pix": torch.tensor(value), "l1": torch.tensor(math.nan)}
        with pytest.raises(FloatingPointError, match=f"step 3: loss term 'pix' is {shown};"):
            check_step(broken, [], "step 3", 3)


def test_gradients_name_the_first_non_finite_parameter_and_pass_large_finite_ones():
    parameters = [torch.zeros(4, requires_grad=True) for _ in range(5)]
    for parameter in parameters:
        parameter.grad = torch.ones(4)
    parameters[0].grad = None  # frozen this step: skipped
    parameters[1].grad[2] = 3.0e38  # finite, its square is not
    named = [(f"p{k}", p) for k, p in enumerate(parameters)]
    total = {"total": torch.tensor(0.5)}
    assert check_step(total, named, "step 7", 7) == {"total": 0.5}
    for value in (math.nan, math.inf, -math.inf):
        parameters[3].grad[1] = value
        parameters[4].grad[0] = math.nan
        with pytest.raises(FloatingPointError, match="step 7: the gradient of 'p3' has NaN/Inf"):
            check_step(total, named, "step 7", 7)
    assert check_step(total, [], "step 7", 7) == {"total": 0.5}


def test_a_guarded_step_reads_the_host_once(monkeypatch):
    """All loss terms and all gradients in one read (``tolist``, which a CPU dispatches no
    operation for; counted here as calls of the guards' reader): on a GPU each read waits for
    the queue, and a step used to make one per term and one per parameter."""
    reads, read = [], guards._host_values

    def counted(tensors):
        reads.append(tensors)
        return read(tensors)

    monkeypatch.setattr(guards, "_host_values", counted)
    parameters = [torch.nn.Parameter(torch.randn(3)) for _ in range(10)]
    optimizer = torch.optim.SGD(parameters, lr=0.1)
    squares = [p.square().sum() for p in parameters]
    terms = {"total": sum(squares), **{f"t{k}": s.detach() for k, s in enumerate(squares[:5])}}
    expected = [p.detach() - 0.1 * 2 * p.detach() for p in parameters]
    with DispatchCount() as count:
        values = descend(
            terms, [(f"p{k}", p) for k, p in enumerate(parameters)], optimizer, "step 0", 0
        )
    assert count.host_reads == 0 and len(reads) == 1
    assert values == {name: float(value) for name, value in terms.items()}
    for parameter, value in zip(parameters, expected):
        torch.testing.assert_close(parameter.detach(), value)


def test_a_guarded_step_refuses_a_non_finite_term_or_gradient_before_the_optimizer_steps():
    """The terms are read after the backward pass now, still before the step: a NaN term is
    named first, then an infinite gradient under a finite loss, and neither moves a parameter."""
    a, b = torch.nn.Parameter(torch.ones(3)), torch.nn.Parameter(torch.zeros(2))
    optimizer = torch.optim.SGD([a, b], lr=0.1)
    named = [("a", a), ("b", b)]
    broken = {"total": a.sum() + b.sqrt().sum(), "pix": torch.tensor(math.nan)}
    with pytest.raises(FloatingPointError, match="step 4: loss term 'pix' is nan;"):
        descend(broken, named, optimizer, "step 4", 4)
    optimizer.zero_grad()
    with pytest.raises(FloatingPointError, match="step 5: the gradient of 'b' has NaN/Inf"):
        descend({"total": a.sum() + b.sqrt().sum()}, named, optimizer, "step 5", 5)
    assert torch.equal(a.detach(), torch.ones(3)) and torch.equal(b.detach(), torch.zeros(2))


def test_the_stages_adam_takes_the_reference_update_and_reads_no_step_count():
    """Fused where PyTorch has the kernel (CUDA; CPU from torch 2.4): the same iterates as the
    single-tensor reference to rounding, over steps and groups with their own learning rates,
    and no step count read back to the host (the default reads one per parameter)."""
    generator = torch.Generator().manual_seed(0)
    shapes = [(5,), (3, 4), (2, 2, 2)]
    start = [torch.randn(shape, generator=generator) for shape in shapes]
    gradients = [[torch.randn(s, generator=generator) for s in shapes] for _ in range(6)]

    def iterate(make):
        parameters = [torch.nn.Parameter(value.clone()) for value in start]
        optimizer = make(
            [{"params": parameters[:2], "lr": 1e-2}, {"params": parameters[2:], "lr": 3e-3}]
        )
        for step in gradients:
            for parameter, gradient in zip(parameters, step):
                parameter.grad = gradient.clone()
            optimizer.step()
        return parameters, optimizer

    ours, optimizer = iterate(lambda groups: adam(groups, eps=1e-15))
    reference, _ = iterate(lambda groups: torch.optim.Adam(groups, eps=1e-15, foreach=False))
    for parameter, expected, first in zip(ours, reference, start):
        assert (parameter.detach() - first).norm() > 1e-3
        torch.testing.assert_close(parameter.detach(), expected.detach(), rtol=2e-6, atol=1e-7)
    assert all(group["fused"] for group in optimizer.param_groups)
    with DispatchCount() as count:
        optimizer.step()
    assert count.host_reads == 0
    assert count.ops["aten::_fused_adam_"] == len(optimizer.param_groups)
