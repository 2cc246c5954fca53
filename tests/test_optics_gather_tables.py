"""The radiance operator's two ways of moving field-group boxes (index tables for small boxes, plain
slices for large ones, :data:`operators._TABLE_MAX_AREA`): each, and a mix of both, against the
float64 per-pixel reference, outputs and gradients, and by gradcheck."""

import pytest
import torch

from controlgs_adapter.downstream.optics import operators
from controlgs_adapter.downstream.optics.bank import PSFBank
from controlgs_adapter.downstream.optics.operators import psf_exact, psf_fast, psf_reference

D64 = torch.float64


def _padded_means(buckets):
    return [sum((bh + 2 * mz) * (bw + 2 * mz) for _, _, bh, bw, mz in bk.boxes) / len(bk.boxes)
            for bks in buckets for bk in bks]


@pytest.fixture(scope="module")
def rb():
    return PSFBank.default().resample_to(24, 24, dtype=D64, radiometry="radiance")


@pytest.mark.parametrize("rule", ["slices", "mixed", "tables"])
@pytest.mark.parametrize("op", ["exact", "fast"])
def test_tables_and_slices_match_the_reference(rb, monkeypatch, rule, op):
    buckets = rb.zones(1, 0.0) if op == "exact" else rb.zones(2, 0.0)   # fast at tol 0: exact, ranks 1..4
    means = sorted(_padded_means(buckets))
    assert means[0] < means[-1]                                  # a threshold between them splits the buckets
    thr = {"slices": 0, "mixed": means[len(means) // 2], "tables": means[-1]}[rule]
    monkeypatch.setattr(operators, "_TABLE_MAX_AREA", thr)
    used = {operators._use_tables(bk) for bks in buckets for bk in bks}
    assert used == {"slices": {False}, "mixed": {False, True}, "tables": {True}}[rule]

    run = (lambda a: psf_exact(a, rb)) if op == "exact" else (lambda a: psf_fast(a, rb, tol=0.0, zone=2))
    x = torch.rand(2, 3, 24, 24, dtype=D64, requires_grad=True)
    w = torch.rand(2, 3, 24, 24, dtype=D64)
    out = run(x)
    (g,) = torch.autograd.grad((out * w).sum(), x)
    ref = psf_reference(x, rb)
    (g_ref,) = torch.autograd.grad((ref * w).sum(), x)
    tol = 1e-12 if op == "exact" else 1e-9     # fast: its eigen-split drops singular values at rounding level (4e-10 here)
    assert torch.allclose(out, ref, atol=tol, rtol=0)
    assert torch.allclose(g, g_ref, atol=tol, rtol=0)


@pytest.mark.parametrize("rule", [0, 10 ** 9])
def test_gradcheck_both_branches(monkeypatch, rule):
    monkeypatch.setattr(operators, "_TABLE_MAX_AREA", rule)
    rb = PSFBank.default().resample_to(6, 6, dtype=D64, radiometry="radiance")
    x = torch.rand(1, 3, 6, 6, dtype=D64, requires_grad=True)
    assert torch.autograd.gradcheck(lambda a: psf_exact(a, rb), (x,))
    assert torch.autograd.gradcheck(lambda a: psf_fast(a, rb, tol=0.0, zone=3), (x,))   # ranks > 1


@pytest.mark.skipif(not torch.cuda.is_available(), reason="no GPU available in this run: the CUDA table rule not run")
def test_cuda_uses_tables_for_every_bucket_and_matches_the_cpu_reference(monkeypatch):
    """On CUDA every bucket moves its boxes through index tables (a Python step per box is ~10 kernel
    launches there), even where the CPU rule picks slices; outputs and gradients equal the float64
    per-pixel reference computed on the CPU."""
    monkeypatch.setattr(operators, "_TABLE_MAX_AREA", 0)            # the CPU rule: slices for every bucket
    bank = PSFBank.default()
    cpu = bank.resample_to(24, 24, dtype=D64, radiometry="radiance")
    x = torch.rand(2, 3, 24, 24, dtype=D64, requires_grad=True)
    xg = x.detach().cuda().requires_grad_(True)
    gpu = bank.resample_to(24, 24, device=xg.device, dtype=D64, radiometry="radiance")   # cuda:0, as the stage does
    assert {operators._use_tables(bk) for bks in cpu.zones(1, 0.0) for bk in bks} == {False}
    assert {operators._use_tables(bk) for bks in gpu.zones(1, 0.0) for bk in bks} == {True}
    w = torch.rand(2, 3, 24, 24, dtype=D64)
    out = psf_exact(xg, gpu)
    (g,) = torch.autograd.grad((out * w.cuda()).sum(), xg)
    ref = psf_reference(x, cpu)
    (g_ref,) = torch.autograd.grad((ref * w).sum(), x)
    assert torch.allclose(out.cpu(), ref, atol=1e-12, rtol=0)
    assert torch.allclose(g.cpu(), g_ref, atol=1e-12, rtol=0)
