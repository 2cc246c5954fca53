"""Importing ColorVideoVDP (``pycvvdp``, the ``cvvdp`` package) beside the CPU torch.

``cvvdp`` is installed with ``--no-deps`` (its ``torchvision`` requirement would replace the CPU torch with
a CUDA build), yet ``pycvvdp`` imports three names from packages left out: ``torchvision.transforms.GaussianBlur``
(the base metric's phase-uncertainty blur, sigma 3 on a 13-tap kernel), ``torchvision.ops.MLP`` and
``huggingface_hub.hf_hub_download`` (both only for the ML variants, whose weights come from a hub: never
downloaded here). :func:`import_pycvvdp` puts stand-ins for the absent packages into ``sys.modules`` for the
import only and takes them out afterwards; an installed ``torchvision`` or ``huggingface_hub`` is used as it is.
"""

from __future__ import annotations

import importlib
import importlib.util
import sys
from collections.abc import Iterator
from contextlib import contextmanager
from types import ModuleType
from typing import Any

import torch
import torch.nn.functional as F
from torch import nn

from .errors import InputValueError, MissingDependencyError

__all__ = ["GaussianBlur", "MLP", "hf_hub_download", "import_pycvvdp", "CVVDP_INSTALL"]

#: how to install ColorVideoVDP without replacing the CPU torch
CVVDP_INSTALL = "pip install 'controlgs-adapter[cvvdp]' && pip install --no-deps cvvdp==0.5.7"


class GaussianBlur(nn.Module):
    """Stand-in for ``torchvision.transforms.GaussianBlur(kernel_size, sigma)`` with a fixed ``sigma`` (what
    ``pycvvdp`` builds): every channel of ``[..., C, H, W]`` is convolved with the normalised Gaussian
    sampled at the integer offsets ``-(k-1)/2 .. (k-1)/2`` (``k = kernel_size``, odd), the image reflect-padded
    by ``k // 2`` on each side (so ``H, W > k // 2``); output of the input's shape and dtype."""

    def __init__(self, kernel_size: int, sigma: float) -> None:
        super().__init__()
        if isinstance(kernel_size, bool) or not isinstance(kernel_size, int) or kernel_size < 1 or kernel_size % 2 == 0:
            raise InputValueError(f"GaussianBlur: kernel_size must be an odd int >= 1, got {kernel_size!r}")
        if isinstance(sigma, bool) or not isinstance(sigma, (int, float)) or not sigma > 0:
            raise InputValueError(f"GaussianBlur: sigma must be a number > 0 (a fixed sigma), got {sigma!r}")
        self.kernel_size, self.sigma = kernel_size, float(sigma)

    def kernel(self, dtype: torch.dtype = torch.float64, device: torch.device | None = None) -> torch.Tensor:
        """The 1-D kernel ``[kernel_size]``, summing to 1."""
        half = (self.kernel_size - 1) / 2
        x = torch.linspace(-half, half, self.kernel_size, dtype=torch.float64)
        g = torch.exp(-0.5 * (x / self.sigma) ** 2)
        return (g / g.sum()).to(device=device, dtype=dtype)

    def forward(self, image: torch.Tensor) -> torch.Tensor:
        h, w = image.shape[-2:]
        k, pad = self.kernel_size, self.kernel_size // 2
        g = self.kernel(image.dtype, image.device)
        x = F.pad(image.reshape(-1, 1, h, w), (pad, pad, pad, pad), mode="reflect")
        x = F.conv2d(F.conv2d(x, g.view(1, 1, 1, k)), g.view(1, 1, k, 1))
        return x.reshape(image.shape)


class MLP:
    """Stand-in for ``torchvision.ops.MLP``: only ColorVideoVDP's ML variants build one; refused."""

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        raise MissingDependencyError("ColorVideoVDP's ML variants need torchvision and hub weights, "
                                     "which are not installed and never downloaded; use pycvvdp.cvvdp")


def hf_hub_download(*args: Any, **kwargs: Any) -> str:
    """Stand-in for ``huggingface_hub.hf_hub_download``: nothing is downloaded; refused."""
    raise MissingDependencyError("ColorVideoVDP's ML variants load weights from a hub, which is never downloaded; "
                                 "use pycvvdp.cvvdp")


def _module(name: str, **attrs: Any) -> ModuleType:
    module = ModuleType(name)
    module.__dict__.update(attrs)
    return module


def _stand_ins() -> dict[str, ModuleType]:
    """The stand-in modules for the packages that are not installed."""
    out: dict[str, ModuleType] = {}
    if importlib.util.find_spec("torchvision") is None:
        transforms, ops = _module("torchvision.transforms", GaussianBlur=GaussianBlur), _module("torchvision.ops", MLP=MLP)
        out |= {"torchvision": _module("torchvision", transforms=transforms, ops=ops),
                "torchvision.transforms": transforms, "torchvision.ops": ops}
    if importlib.util.find_spec("huggingface_hub") is None:
        out["huggingface_hub"] = _module("huggingface_hub", hf_hub_download=hf_hub_download)
    return out


@contextmanager
def _installed(modules: dict[str, ModuleType]) -> Iterator[None]:
    """``modules`` in ``sys.modules`` inside the block only."""
    sys.modules.update(modules)
    try:
        yield
    finally:
        for name, module in modules.items():
            if sys.modules.get(name) is module:
                del sys.modules[name]


def import_pycvvdp() -> ModuleType:
    """``pycvvdp``, imported with stand-ins for torchvision and huggingface_hub where they are absent.

    Raises :class:`MissingDependencyError` (one line, with the install command) when ``cvvdp`` or one of
    the packages it imports is not installed, or does not import."""
    module = sys.modules.get("pycvvdp")
    if module is not None:
        return module
    try:
        with _installed(_stand_ins()):
            return importlib.import_module("pycvvdp")
    except (ImportError, RuntimeError, AttributeError) as e:
        raise MissingDependencyError(f"ColorVideoVDP does not import ({type(e).__name__}: {e}); {CVVDP_INSTALL}") from None
