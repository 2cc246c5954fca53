"""PSFBank: every numeric argument is checked, naming it."""

from __future__ import annotations

import math

import pytest
import torch

from controlgs_adapter.downstream.optics.bank import PSFBank
from controlgs_adapter.errors import InputValueError

D64 = torch.float64


def _args(**over):
    L, G, K = 3, 2, 3
    psf = torch.rand(L, G, G, K, K, dtype=D64, generator=torch.Generator().manual_seed(0))
    psf /= psf.sum((-1, -2), keepdim=True)
    c = torch.linspace(-1, 1, 3, dtype=D64)
    cy, cx = torch.meshgrid(c, c, indexing="ij")
    f = torch.tensor([-0.5, 0.5], dtype=D64)
    args = dict(psf=psf, psf_pitch_mm=torch.full((L, G, G), 0.1, dtype=D64), field_x=f, field_y=f.clone(),
                chief=torch.stack([cx, cy], -1).expand(L, 3, 3, 2).clone(), chief_x=c, chief_y=c.clone(),
                wavelengths_nm=(656.0, 550.0, 486.0), display_mm=(24.0, 24.0))
    return {**args, **over}


@pytest.mark.parametrize("value", [(math.nan, math.nan), (24.0, math.inf), (24.0, -1.0), (0.0, 24.0), (24.0,),
                                   (24.0, 24.0, 24.0), "24x24", (True, 24.0), ("24", "24"), None, 24.0])
def test_display_mm_must_be_two_finite_positive_numbers(value):
    with pytest.raises(InputValueError, match=r"^PSF bank: display_mm must be"):
        PSFBank(**_args(display_mm=value))


@pytest.mark.parametrize("value", [(656.0, math.nan, 486.0), (656.0, 550.0, -486.0), (656.0, 0.0, 486.0),
                                   (656.0, "550", 486.0), (656.0, math.inf, 486.0), "656", None])
def test_wavelengths_must_be_finite_positive_numbers(value):
    with pytest.raises(InputValueError, match=r"^PSF bank: wavelengths_nm must be"):
        PSFBank(**_args(wavelengths_nm=value))


@pytest.mark.parametrize("name", ["psf", "psf_pitch_mm", "field_x", "field_y", "chief", "chief_x", "chief_y"])
def test_each_tensor_must_be_a_floating_point_tensor(name):
    args = _args()
    with pytest.raises(InputValueError, match=rf"^PSF bank: {name} must be a floating-point torch.Tensor, got torch.int64"):
        PSFBank(**{**args, name: args[name].long()})
    with pytest.raises(InputValueError, match=rf"^PSF bank: {name} must be a floating-point torch.Tensor, got list"):
        PSFBank(**{**args, name: args[name].tolist()})


@pytest.mark.parametrize("name", ["psf_pitch_mm", "field_x", "chief", "chief_y"])
def test_each_tensor_must_be_finite(name):
    args = _args()
    bad = args[name].clone()
    bad.view(-1)[0] = math.nan
    with pytest.raises(InputValueError, match=rf"^PSF bank: {name} holds 1 NaN/Inf"):
        PSFBank(**{**args, name: bad})


def test_numbers_of_any_real_type_are_taken_as_floats():
    bank = PSFBank(**_args(display_mm=[24, 30], wavelengths_nm=[656, 550.5, 486]))
    assert bank.display_mm == (24.0, 30.0) and bank.wavelengths_nm == (656.0, 550.5, 486.0)
    assert all(isinstance(v, float) for v in (*bank.display_mm, *bank.wavelengths_nm))
