"""LensPrewarp.for_optics / fit_bank_prewarp name what is wrong with the optics stage they are given."""

from __future__ import annotations

import pytest
from torch import nn

from controlgs_adapter import plugins
from controlgs_adapter.downstream.lens import BankMap, LensPrewarp
from controlgs_adapter.errors import InputValueError


def test_a_stage_without_a_psf_bank_is_refused_by_name():
    with pytest.raises(InputValueError, match="PSFBank.*Identity.*NoneType"):
        LensPrewarp.for_optics(nn.Identity())


@pytest.mark.skipif("optics" not in plugins.stages(), reason="optics stage not registered")
def test_the_optics_placement_is_checked_and_followed():
    from controlgs_adapter.downstream.optics.stage import PSFOptics
    from controlgs_adapter.downstream.prewarp_fit import fit_bank_prewarp

    optics = PSFOptics(mode="distortion", placement="stretch")
    lens = LensPrewarp.for_optics(optics, source="chief_rays")
    assert isinstance(lens.map, BankMap) and lens.map.placement == "stretch"
    optics.placement = "tile"
    with pytest.raises(InputValueError, match="placement.*'tile'"):
        LensPrewarp.for_optics(optics, source="chief_rays")
    with pytest.raises(InputValueError, match="placement.*'tile'"):
        fit_bank_prewarp(optics, 16, modes=("distortion",))
