"""set_optics_mode: the evaluation pipeline's optics stage runs in the requested mode, or the call fails."""

from __future__ import annotations

import pytest
import torch

from controlgs_adapter import plugins
from controlgs_adapter.downstream.pipeline import Pipeline
from controlgs_adapter.downstream.stage import Stage, StageContext
from controlgs_adapter.errors import InputValueError
from controlgs_adapter.downstream.optics.stage import set_optics_mode
from controlgs_adapter.evaluation import make_pipeline
from controlgs_adapter.state import RuntimeState


class _ModelessOptics(Stage):
    """A third-party optics stage with no ``mode``."""

    name = "optics"
    order = 50.0

    def process(self, image: torch.Tensor, state: RuntimeState, ctx: StageContext) -> torch.Tensor:
        return image


def test_make_pipeline_sets_each_optics_mode():
    if "optics" not in plugins.stages():
        pytest.skip("optics stage not registered")
    for mode in ("distortion", "fast", "exact"):
        assert make_pipeline({"optics": True}, mode)["optics"].mode == mode


def test_an_optics_stage_without_modes_is_refused_not_silently_ignored():
    with pytest.raises(InputValueError, match="PSFOptics.*_ModelessOptics"):
        set_optics_mode(Pipeline([_ModelessOptics()]), "fast")
    pipeline = Pipeline.from_config({"resample": True})  # no optics stage: nothing to set
    set_optics_mode(pipeline, "fast")
    assert "optics" not in pipeline
