"""Non-strict adapter loads (PEFT's ``strict=False``) and several named adapters on one wrapped model."""

from __future__ import annotations

import pytest
import torch

from controlgs_adapter import ControlGS, RuntimeState
from controlgs_adapter.controlgs import ADAPTER_FORMAT_VERSION, ADAPTER_KIND
from controlgs_adapter.errors import IncompatibleAdapterError, InputValueError, LifecycleError
from controlgs_adapter.formats.safetensors import load_tensors

from _adapter_files import rewrite, trained
from scaffold_standin import ScaffoldStandIn, make_camera

STATE = RuntimeState(downsample=5.0, power_saving=0.55)
DECODERS = ("mlp_opacity", "mlp_cov", "mlp_color")


def outputs(cgs, model, cam, x):
    with torch.no_grad(), cgs.conditioned(STATE, camera=cam):
        return model.decode(x)


def saved_adapter(tmp_path, seed: int = 7, file: str = "a.safetensors", **kw):
    model = ScaffoldStandIn(30, seed=0)
    cgs = trained(model, seed, **kw)
    path = cgs.save(tmp_path / file)
    cgs.unwrap()
    return path


def test_non_strict_skips_extra_and_missing_modules_and_loads_the_rest_exactly(tmp_path):
    path = saved_adapter(tmp_path)
    tensors, header = load_tensors(path, kind=ADAPTER_KIND, max_version=ADAPTER_FORMAT_VERSION)
    extra_target = {"decoder": "mlp_nothing", "fc1": "mlp_nothing.0", "in_features": 35, "out_features": 32}
    rewrite(path, {"targets": header["targets"] + [extra_target]}, tensor_changes={"extra.bias": torch.zeros(3)},
            drop=("projections.display.d32.weight",))
    with pytest.raises(IncompatibleAdapterError):  # strict stays the default
        ControlGS.load(path, ScaffoldStandIn(30, seed=0))
    model = ScaffoldStandIn(30, seed=0)
    with pytest.warns(RuntimeWarning, match="non-strict load skipped"):
        cgs = ControlGS.load(path, model, strict=False)
    assert len(cgs.skipped) == 3
    assert cgs.skipped[0].startswith("target 'mlp_nothing': ")
    assert cgs.skipped[1:] == ["tensors missing from the file: ['projections.display.d32.weight']",
                               "unexpected tensors in the file: ['extra.bias']"]
    assert [t.decoder for t in cgs.targets] == list(DECODERS)
    state = cgs.injector.state_dict()
    for k, v in tensors.items():
        if k != "projections.display.d32.weight":
            assert torch.equal(state[k], v), k


def test_non_strict_skips_a_misshapen_projection_and_conditions_of_another_anchor_count(tmp_path):
    path = saved_adapter(tmp_path)
    tensors = rewrite(path, tensor_changes={"projections.lens.d32.weight": torch.ones(32, 7)})
    model = ScaffoldStandIn(30, seed=0)
    with pytest.warns(RuntimeWarning):
        cgs = ControlGS.load(path, model, strict=False)
    assert cgs.skipped == ["tensor 'projections.lens.d32.weight': shape [32, 7], expected [32, 8]"]
    state = cgs.injector.state_dict()
    assert state["projections.lens.d32.weight"].shape == (32, 8)
    assert all(torch.equal(state[k], v) for k, v in tensors.items() if k != "projections.lens.d32.weight")
    cgs.unwrap()

    other = ScaffoldStandIn(31, seed=0)  # other anchors: conditions skipped (stay zero), projections load
    with pytest.warns(RuntimeWarning, match=r"backbone fingerprint.*\(loaded anyway\)"):
        cgs = ControlGS.load(path, other, strict=False)
    assert cgs.skipped == ["anchor count: the adapter has 30 anchors, the model 31",
                           "tensor 'projections.lens.d32.weight': shape [32, 7], expected [32, 8]"]
    assert torch.equal(cgs.injector.conditions.detach(), torch.zeros(31, 3, 8))
    assert torch.equal(cgs.injector.state_dict()["projections.display.d32.weight"], tensors["projections.display.d32.weight"])


def test_non_strict_still_refuses_what_cannot_be_skipped(tmp_path):
    path = saved_adapter(tmp_path)
    with pytest.raises(IncompatibleAdapterError, match="none of the adapter's targets fits"):
        ControlGS.load(path, ScaffoldStandIn(30, feat_dim=16), strict=False)
    rewrite(path, {"backend": "octree_gs"})
    with pytest.raises(IncompatibleAdapterError, match="recognised by scaffold_gs"):
        ControlGS.load(path, ScaffoldStandIn(30, seed=0), strict=False)


def test_named_adapters_switch_and_each_equals_a_model_with_only_that_adapter(tmp_path):
    cam = make_camera()
    path_a = saved_adapter(tmp_path, 7, "a.safetensors")
    path_b = saved_adapter(tmp_path, 8, "b.safetensors", modules=("lens", "display"), cond_dim=4, state_blind=True)
    model = ScaffoldStandIn(30, seed=0)
    x = model.decoder_input(cam.center)
    cgs = ControlGS.load(path_a, model, name="a")
    assert cgs.load_adapter(path_b, name="b") == []
    assert cgs.adapters == ("a", "b") and cgs.active_adapter == "a"
    out_a = outputs(cgs, model, cam, x)
    cgs.set_adapter("b")
    assert cgs.modules == ("lens", "display") and cgs.state_blind
    out_b = outputs(cgs, model, cam, x)
    assert not torch.equal(out_a["color"], out_b["color"])
    cgs.set_adapter("a")
    assert all(torch.equal(out_a[k], v) for k, v in outputs(cgs, model, cam, x).items())
    cgs.set_adapter("b")
    resaved = cgs.save(tmp_path / "b2.safetensors")  # save() writes the active adapter
    with torch.no_grad():  # outside a block: the backbone
        plain, got = ScaffoldStandIn(30, seed=0).decode(x), model.decode(x)
    assert all(torch.equal(plain[k], got[k]) for k in plain)
    cgs.unwrap()

    for path, want in ((path_a, out_a), (path_b, out_b), (resaved, out_b)):
        alone_model = ScaffoldStandIn(30, seed=0)
        alone = ControlGS.load(path, alone_model)
        got = outputs(alone, alone_model, cam, x)
        assert all(torch.equal(want[k], got[k]) for k in want), path


def test_unknown_or_duplicate_adapter_names_are_clear_errors(tmp_path):
    path = saved_adapter(tmp_path)
    model = ScaffoldStandIn(30, seed=0)
    cgs = ControlGS.load(path, model)
    cgs.load_adapter(path, name="second")
    with pytest.raises(InputValueError, match=r"unknown adapter 'third'; loaded adapters: \['default', 'second'\]"):
        cgs.set_adapter("third")
    with pytest.raises(InputValueError, match="already loaded"):
        cgs.load_adapter(path, name="second")
    with torch.no_grad(), cgs.conditioned(STATE, camera=make_camera(), on_miss="ignore"):
        with pytest.raises(LifecycleError):
            cgs.set_adapter("second")
