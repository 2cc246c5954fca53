"""Tests of ``controlgs_adapter.cvvdp_shim``: the GaussianBlur stand-in against a float64 blur written from its
definition, the refusing ML stand-ins, and importing ColorVideoVDP with the stand-ins in ``sys.modules`` only
for the import."""

from __future__ import annotations

import importlib.util
import re
import sys

import numpy as np
import pytest
import torch

from controlgs_adapter.cvvdp_shim import MLP, GaussianBlur, hf_hub_download, import_pycvvdp
from controlgs_adapter.errors import InputValueError, MissingDependencyError

HAS_TORCHVISION = importlib.util.find_spec("torchvision") is not None
HAS_HUB = importlib.util.find_spec("huggingface_hub") is not None
needs_cvvdp = pytest.mark.skipif(importlib.util.find_spec("pycvvdp") is None, reason="needs cvvdp (scripts/setup.sh installs it)")


def blur_reference(img: np.ndarray, k: int, sigma: float) -> np.ndarray:
    """float64 Gaussian blur of ``[..., H, W]`` by its definition: ``out[y, x] = sum_ij w_i w_j img[m(y + i), m(x + j)]``
    with ``w_i`` proportional to ``exp(-i^2 / (2 sigma^2))``, ``|i| <= k // 2``, summing to 1, and ``m`` mirroring an
    index about the edge pixel (-1 -> 1, n -> n - 2)."""
    r = k // 2
    w = np.exp(-0.5 * (np.arange(-r, r + 1) / sigma) ** 2)
    w /= w.sum()
    h, wd = img.shape[-2:]

    def m(i: int, n: int) -> int:
        i = abs(i)
        return 2 * (n - 1) - i if i > n - 1 else i

    out = np.zeros(img.shape, dtype=np.float64)
    for y in range(h):
        for x in range(wd):
            for i in range(-r, r + 1):
                for j in range(-r, r + 1):
                    out[..., y, x] += w[i + r] * w[j + r] * img[..., m(y + i, h), m(x + j, wd)]
    return out


@pytest.mark.parametrize("k, sigma, shape", [(13, 3, (2, 3, 9, 11)), (13, 3.0, (1, 1, 7, 20)), (5, 0.7, (3, 6, 5)),
                                             (33, 8, (1, 17, 18)), (1, 2.0, (4, 4))])
def test_gaussian_blur_is_the_definition(k, sigma, shape):
    g = torch.Generator().manual_seed(k)
    img = torch.rand(shape, generator=g, dtype=torch.float64)
    ref = blur_reference(img.numpy(), k, float(sigma))
    out = GaussianBlur(k, sigma)(img)
    assert out.shape == img.shape and out.dtype == torch.float64
    np.testing.assert_allclose(out.numpy(), ref, rtol=0, atol=1e-12)
    out32 = GaussianBlur(k, sigma)(img.float())
    assert out32.dtype == torch.float32
    np.testing.assert_allclose(out32.numpy(), ref, rtol=0, atol=2e-6)
    kernel = GaussianBlur(k, sigma).kernel()
    assert float(kernel.sum()) == pytest.approx(1.0, abs=1e-15) and torch.equal(kernel, kernel.flip(0))


def test_gaussian_blur_gradients():
    img = torch.rand(1, 2, 8, 9, dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(GaussianBlur(5, 1.3), (img,))


@pytest.mark.parametrize("k, sigma, name", [(4, 1.0, "kernel_size"), (0, 1.0, "kernel_size"), (3.0, 1.0, "kernel_size"),
                                            (True, 1.0, "kernel_size"), (5, 0.0, "sigma"), (5, (0.1, 2.0), "sigma"),
                                            (5, float("nan"), "sigma")])
def test_gaussian_blur_refusals_name_the_argument(k, sigma, name):
    value = re.escape(repr(sigma if name == "sigma" else k))
    with pytest.raises(InputValueError, match=rf"^GaussianBlur: {name} .*got {value}$"):
        GaussianBlur(k, sigma)


def test_ml_stand_ins_refuse_without_downloading():
    with pytest.raises(MissingDependencyError, match="ML variants"):
        MLP(in_channels=4, hidden_channels=[8, 1])
    with pytest.raises(MissingDependencyError, match="never downloaded"):
        hf_hub_download(repo_id="any", filename="model.pt")


@needs_cvvdp
def test_import_uses_the_stand_ins_for_the_import_only(monkeypatch):
    for name in [m for m in sys.modules if m == "pycvvdp" or m.startswith("pycvvdp.")]:
        monkeypatch.delitem(sys.modules, name)  # a fresh import (monkeypatch puts the modules back afterwards)
    pycvvdp = import_pycvvdp()
    assert import_pycvvdp() is pycvvdp and hasattr(pycvvdp, "cvvdp")
    metric_module = sys.modules["pycvvdp.cvvdp_metric"]
    ml_module = sys.modules["pycvvdp.cvvdp_ml_metric"]
    if not HAS_TORCHVISION:
        assert metric_module.GaussianBlur is GaussianBlur and ml_module.MLP is MLP
        assert not any(m == "torchvision" or m.startswith("torchvision.") for m in sys.modules)
    if not HAS_HUB:
        assert ml_module.hf_hub_download is hf_hub_download and "huggingface_hub" not in sys.modules


def test_import_refusal_names_the_install(monkeypatch):
    monkeypatch.setitem(sys.modules, "pycvvdp", None)  # what Python does for a package that is absent
    with pytest.raises(MissingDependencyError, match=r"^ColorVideoVDP does not import .*pip install --no-deps cvvdp==0\.5\.7$"):
        import_pycvvdp()
