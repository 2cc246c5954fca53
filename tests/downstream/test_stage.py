"""Tests of ``controlgs_adapter.downstream.stage``."""

from __future__ import annotations

import pytest
import torch

from controlgs_adapter.downstream.display import DisplayMapping
from controlgs_adapter.downstream.foveation import Foveation
from controlgs_adapter.downstream.lens import LensPrewarp
from controlgs_adapter.downstream.oled import OLEDEmission
from controlgs_adapter.downstream.optics.stage import PSFOptics
from controlgs_adapter.downstream.pipeline import Pipeline
from controlgs_adapter.downstream.resample import AreaResample
from controlgs_adapter.downstream.stage import Stage, StageContext
from controlgs_adapter.errors import InputValueError
from controlgs_adapter.state import RuntimeState


def test_plugin_stage_after_an_absent_anchor_follows_the_last_stage_ordered_before_it():
    """A stage ``after="resample"`` in a pipeline without resampling goes after the last built-in whose
    registered order is at most resample's (20): foveation (5), lens (10), then it, then display (30)."""
    from controlgs_adapter.downstream.display import DisplayMapping
    from controlgs_adapter.downstream.foveation import Foveation
    from controlgs_adapter.downstream.lens import LensPrewarp
    from controlgs_adapter.downstream.pipeline import Pipeline
    from controlgs_adapter.downstream.stage import Stage

    class After(Stage):
        name = "after_resample"
        domain = "srgb"
        after = "resample"

        def forward(self, image, state, ctx):
            return image

    p = Pipeline([DisplayMapping(), After(), LensPrewarp(), Foveation()])
    assert p.names == ["foveation", "lens", "after_resample", "display"]


D = torch.float64


def _img(values: list[float], h: int = 1, w: int = 1) -> torch.Tensor:
    """A [3, h, w] float64 image with channel c constant at values[c]."""
    return torch.tensor(values, dtype=D)[:, None, None].expand(3, h, w).clone()


class _Probe(Stage):
    name = "probe"

    def process(self, image, state, ctx):
        self.seen = (state, ctx)
        return image * 2


def _ordered(order: float) -> Stage:
    return type(f"At{order}".replace(".", "_"), (Stage,), {"name": f"at{order}", "order": order,
                                                         "process": lambda self, i, s, c: i})()


def test_display_stage_options_and_records():
    with pytest.raises(InputValueError, match="p_ref must be 'displayed' or 'ground_truth'"):
        DisplayMapping(p_ref="eye")
    st = DisplayMapping()
    assert st.order == 30.0 and st.wants_displayed_reference and st.brighten
    assert not DisplayMapping(p_ref="ground_truth").wants_displayed_reference
    s0 = RuntimeState(power_saving=0.0)
    assert st.is_identity(s0) and st.is_identity(s0, StageContext((2, 2)))
    assert not st.is_identity(s0, StageContext((2, 2), reference=_img([1.0, 1.0, 1.0], 2, 2)))
    assert not st.is_identity(RuntimeState(power_saving=0.1))
    # ground truth as given (sRGB): P_ref of encoded 0.5 grey = 0.21404114 * 1001.82
    gt = DisplayMapping(p_ref="ground_truth", brighten=False)
    img = _img([0.5, 0.5, 0.5], 2, 2)
    rec: dict = {}
    out = gt(img, RuntimeState(power_saving=0.0), StageContext((2, 2), reference=_img([0.5] * 3, 2, 2), record=rec))
    assert float(rec["display.power_ref"]) == pytest.approx(0.21404114 * 1001.82, rel=1e-7)
    assert float(rec["display.scale"]) == pytest.approx(0.21404114 / 0.5, rel=1e-7)
    assert set(rec) == {"display.scale", "display.power_target", "display.power", "display.clipped_fraction",
                        "display.power_ref"}
    assert torch.allclose(out, img * 0.21404114 / 0.5)
    # brighten=False stage: a brighter reference does not scale up
    rec2: dict = {}
    gt(img, RuntimeState(), StageContext((2, 2), reference=_img([1.0] * 3, 2, 2), record=rec2))
    assert float(rec2["display.scale"]) == 1.0
    # displayed reference (linear) wins over the sRGB reference when p_ref="displayed"
    rec3: dict = {}
    ctx = StageContext((2, 2), reference=_img([1.0] * 3, 2, 2), record=rec3, displayed_reference=_img([0.25] * 3, 2, 2))
    st(img, RuntimeState(), ctx)
    assert float(rec3["display.power_ref"]) == pytest.approx(0.25 * 1001.82)
    assert float(rec3["display.scale"]) == pytest.approx(0.5)
    # no reference: no power_ref recorded, scale 1 - rho
    rec4: dict = {}
    st(img, RuntimeState(power_saving=0.2), StageContext((2, 2), record=rec4))
    assert "display.power_ref" not in rec4 and float(rec4["display.scale"]) == pytest.approx(0.8)


def test_stage_defaults_and_resolve():
    p = _Probe()
    img = torch.ones(2, 3, 4, 5, dtype=D)
    assert torch.equal(p(img), img * 2)
    state, ctx = p.seen
    assert state == RuntimeState() and ctx.native_size == (4, 5) and ctx.reference is None and ctx.record is None
    s = RuntimeState(downsample=2.0)
    c = StageContext((8, 10))
    p(img, s, c)
    assert p.seen == (s, c)
    assert not p.is_identity(s) and p.domain == "linear" and p.after is None and p.before is None
    with pytest.raises(NotImplementedError):
        Stage().process(img, s, c)


def test_default_orders_of_the_stages():
    # a third-party stage without an order runs after every built-in (order 100 > 50)
    plain = type("Plain", (Stage,), {"name": "plain", "process": lambda self, i, s, c: i})()
    pipe = Pipeline([plain, _ordered(100.1), _ordered(99.9), OLEDEmission(), Foveation(), _ordered(4.9),
                     _ordered(5.1), AreaResample(), DisplayMapping(), _ordered(29.9), _ordered(30.1),
                     _ordered(19.9), _ordered(20.1), _ordered(39.9), _ordered(40.1)])
    assert pipe.names == ["at4.9", "foveation", "at5.1", "at19.9", "resample", "at20.1", "at29.9", "display",
                          "at30.1", "at39.9", "oled", "at40.1", "at99.9", "plain", "at100.1"]


def test_lens_runs_at_order_ten():
    def at(order: float) -> Stage:
        return type("S", (Stage,), {"name": f"s{order}", "order": order, "process": lambda self, i, s, c: i})()

    assert Pipeline([at(10.1), LensPrewarp(), at(9.9)]).names == ["s9.9", "lens", "s10.1"]


def test_optics_runs_last_after_a_stage_ordered_between():
    """Stage order 50: a third-party stage at order 45 runs before it, one at 55 after it."""
    from controlgs_adapter.downstream.pipeline import Pipeline
    from controlgs_adapter.downstream.stage import Stage

    class S(Stage):
        def process(self, image, state, ctx):
            return image

    a, b = S(), S()
    a.name, a.order, b.name, b.order = "a45", 45.0, "b55", 55.0
    assert Pipeline([b, PSFOptics(mode="distortion"), a]).names == ["a45", "optics", "b55"]
