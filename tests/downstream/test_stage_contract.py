"""Every registered built-in stage, and every colour conversion module, keeps the stage contract of
:func:`helpers.stage_contract.check_stage` (identity when off, shapes, dtypes, devices, gradients,
functional twin, pipeline)."""

from __future__ import annotations

from typing import Any, Callable

import pytest
import torch
from helpers.stage_contract import check_stage

from controlgs_adapter import RuntimeState, plugins
from controlgs_adapter.downstream import color
from controlgs_adapter.downstream.display import DisplayMapping, display_mapping
from controlgs_adapter.downstream.foveation import Foveation, FoveationModel, foveation
from controlgs_adapter.downstream.lens import DisplayLUTMap, LensPrewarp, lens_prewarp
from controlgs_adapter.downstream.oled import OLEDEmission, oled_emission
from controlgs_adapter.downstream.optics.stage import PSFOptics, psf_optics
from controlgs_adapter.downstream.resample import AreaResample, area_resample


def _lens(stage: LensPrewarp) -> dict[str, Any]:
    def twin(x, s, c):
        return lens_prewarp(x, *stage.map(tuple(x.shape[-2:]), x.dtype, x.device), basis=stage.basis,
                            supersample=stage.supersample)

    return dict(stage=stage, functional=twin)


def _display_lut() -> LensPrewarp:
    g = torch.Generator().manual_seed(0)
    table = (0.01 * torch.randn(3, 5, 5, 2, generator=g), 1 + 0.1 * torch.rand(3, 5, 5, generator=g))
    return LensPrewarp(DisplayLUTMap({"exact": table}))


def _optics(mode: str) -> dict[str, Any]:
    stage = PSFOptics(mode=mode)
    return dict(stage=stage, functional=lambda x, s, c: psf_optics(x, stage.bank, mode), size=(5, 9), meta=False)


#: name of a registered stage -> configurations (id, keyword arguments of check_stage)
CASES: dict[str, list[tuple[str, Callable[[], dict[str, Any]]]]] = {
    "foveation": [("foveation", lambda: dict(
        stage=Foveation(FoveationModel(slope=1.0)), functional=lambda x, s, c: foveation(x, s.gaze, preset=FoveationModel(slope=1.0)),
        state=RuntimeState(gaze=(3.0, -2.0)), off_state=RuntimeState(2.0, 0.5)))],
    "lens": [
        ("lens-cardboard-primaries", lambda: _lens(LensPrewarp())),
        ("lens-cardboard-rgb", lambda: _lens(LensPrewarp(basis="rgb"))),
        ("lens-display-lut", lambda: _lens(_display_lut())),
        ("lens-supersampled", lambda: _lens(LensPrewarp(basis="rgb", supersample=2))),
        ("lens-identity-map", lambda: {**_lens(LensPrewarp(coefficients=[[0.0]] * 3)), "off_state": RuntimeState()}),
    ],
    "resample": [
        (f"resample-d{d}", lambda d=d, out=out: dict(
            stage=AreaResample(), functional=lambda x, s, c: area_resample(x, s.downsample),
            state=RuntimeState(downsample=d), off_state=RuntimeState(), size=(7, 6), out_size=out))
        for d, out in ((2.0, (4, 3)), (2.6, (3, 2)))
    ],
    "display": [("display", lambda: dict(
        stage=DisplayMapping(), reference=True, meta=False, state=RuntimeState(power_saving=0.3), off_state=RuntimeState(downsample=2.0),
        functional=lambda x, s, c: display_mapping(
            x, s.power_saving, None if c.reference is None else color.srgb_to_linear(c.reference))))],
    "oled": [
        (f"oled-{name}", lambda d=d, native=native: dict(
            stage=OLEDEmission(), functional=lambda x, s, c: oled_emission(x, c.native_size),
            state=RuntimeState(downsample=d), off_state=RuntimeState(), size=(3, 4), native_size=native,
            out_size=native))
        for name, d, native in (("integer", 2.0, (6, 8)), ("non-integer", 2.5, (7, 9)))
    ],
    "optics": [(f"optics-{mode}", lambda mode=mode: _optics(mode)) for mode in ("distortion", "exact")],
}

CONVERSIONS = {
    "srgb_to_linear": (color.SRGBToLinear, color.srgb_to_linear),
    "linear_to_srgb": (color.LinearToSRGB, color.linear_to_srgb),
    "rgb_to_primaries": (color.RGBToPrimaries, color.rgb_to_primaries),
    "primaries_to_rgb": (color.PrimariesToRGB, color.primaries_to_rgb),
}


def test_every_registered_built_in_stage_has_contract_cases():
    builtin = {name for name, info in plugins.stages().items() if info.plugin == "controlgs_adapter.downstream.builtin"}
    assert builtin == set(CASES)


@pytest.mark.parametrize("make", [make for cases in CASES.values() for _, make in cases],
                         ids=[case_id for cases in CASES.values() for case_id, _ in cases])
def test_built_in_stage_keeps_the_contract(make):
    check_stage(**make())


@pytest.mark.parametrize("name", list(CONVERSIONS))
def test_colour_conversion_keeps_the_contract(name):
    module, functional = CONVERSIONS[name]
    check_stage(module(), lambda x, s, c: functional(x))
