"""Tests of ``controlgs_adapter.downstream.foveation``: the foveation stage is a named placeholder, the
identity at every state (always skipped), placed before the lens pre-warp. The stage contract is checked
in ``test_stage_contract.py``."""

from __future__ import annotations

import torch

from controlgs_adapter.downstream.foveation import Foveation, foveation
from controlgs_adapter.downstream.lens import LensPrewarp
from controlgs_adapter.downstream.pipeline import Pipeline
from controlgs_adapter.downstream.stage import StageContext
from controlgs_adapter.state import RuntimeState


def test_foveation_is_an_identity_stub_before_the_lens():
    image = torch.rand(3, 5, 4)
    stage = Foveation()
    for s in (RuntimeState(), RuntimeState(gaze=(0.5, -0.5), downsample=2.0, power_saving=0.3)):
        assert stage.is_identity(s) and stage.is_identity(s, StageContext((5, 4), reference=image))
    gazing = RuntimeState(gaze=(0.3, -0.2))
    assert foveation(image, (0.3, -0.2)) is image and foveation(image, None) is image
    assert stage(image, gazing) is image and stage(image, gazing, StageContext((5, 4))) is image
    assert stage.name == "foveation" and stage.domain == "linear" and stage.order == 5.0 < LensPrewarp.order
    p = Pipeline.from_config({"foveation": True, "lens": True, "oled": False})
    assert p.names == ["foveation", "lens"] and p.active(gazing) == ["lens"]
