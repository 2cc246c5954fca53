"""ColorVideoVDP called by hand, the reference of the library's ``cvvdp`` scores, and the skip mark of its tests."""

from __future__ import annotations

import pytest
import torch

from controlgs_adapter.cvvdp_shim import import_pycvvdp
from controlgs_adapter.metrics import cvvdp_missing

#: the ``cvvdp`` column, when the package imports here
CVVDP_COLUMN: list[str] = ["cvvdp"] if cvvdp_missing() is None else []
needs_cvvdp = pytest.mark.skipif(not CVVDP_COLUMN, reason="needs cvvdp (scripts/setup.sh installs it)")


def direct_cvvdp(test: torch.Tensor, reference: torch.Tensor, ppd: float) -> float:
    """The package called by hand on ``[3, H, W]`` sRGB images: a ``W x H`` display geometry at ``ppd``,
    standard_4k photometry, HWC float32 on the CPU."""
    pycvvdp = import_pycvvdp()
    h, w = test.shape[-2:]
    metric = pycvvdp.cvvdp(display_name="standard_4k", display_geometry=pycvvdp.vvdp_display_geometry((w, h), ppd=ppd),
                           device=torch.device("cpu"), quiet=True)
    jod, _ = metric.predict(test.permute(1, 2, 0).float().cpu(), reference.permute(1, 2, 0).float().cpu(), dim_order="HWC")
    return float(jod)
