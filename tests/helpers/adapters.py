"""Adapters with random (non-zero) conditions, so that ControlGS differs from the SS-backbone in tests of what renders it."""

from __future__ import annotations

from typing import Any

import torch

from controlgs_adapter import ControlGS


def random_adapter(model: Any, path: Any, seed: int = 0, **wrap: Any) -> Any:
    """An adapter with random conditions (ControlGS then differs from the SS-backbone); ``wrap``:
    :meth:`ControlGS.wrap`'s options."""
    cgs = ControlGS.wrap(model, **wrap)
    g = torch.Generator().manual_seed(seed)
    with torch.no_grad():
        cgs.injector.conditions.copy_(torch.randn(cgs.injector.conditions.shape, generator=g) * 0.5)
    cgs.save(path)
    cgs.unwrap()
    return path
