"""Tests of ``controlgs_adapter.downstream.foveation``."""

from __future__ import annotations

import torch

from controlgs_adapter.downstream.foveation import Foveation, foveation
from controlgs_adapter.downstream.lens import LensPrewarp
from controlgs_adapter.downstream.pipeline import Pipeline
from controlgs_adapter.downstream.stage import StageContext
from controlgs_adapter.state import RuntimeState


def test_foveation_stub_is_identity():
    img = torch.rand(3, 4, 4)
    stage = Foveation()
    assert stage.is_identity(RuntimeState(gaze=(0.2, -0.1)))
    assert stage(img, RuntimeState(gaze=(0.2, -0.1)), StageContext((4, 4))) is img
    assert foveation(img, None) is img


def test_foveation_is_always_the_identity():
    st = Foveation()
    img = torch.rand(3, 2, 2)
    for s in (RuntimeState(), RuntimeState(gaze=(0.5, -0.5), downsample=2.0, power_saving=0.3)):
        assert st.is_identity(s) and st.is_identity(s, StageContext((2, 2), reference=img))
    assert st(img, RuntimeState(gaze=(0.1, 0.1))) is img
    assert foveation(img, None) is img


def test_foveation_is_an_identity_stub_before_the_lens():
    image = torch.rand(3, 5, 4)
    gazing = RuntimeState(gaze=(0.3, -0.2))
    stage = Foveation()
    assert stage.is_identity(gazing) and stage.is_identity(RuntimeState(2.0, 0.5))
    assert foveation(image, (0.3, -0.2)) is image and stage(image, gazing) is image
    assert stage.name == "foveation" and stage.domain == "linear" and stage.order < LensPrewarp.order
    p = Pipeline.from_config({"foveation": True, "lens": True, "oled": False})
    assert p.names == ["foveation", "lens"] and p.active(gazing) == ["lens"]
