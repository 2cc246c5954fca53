"""ControlGS.wrap refuses targets that share a first layer (the injection would be doubled), before it
changes anything on the model."""

from __future__ import annotations

import pytest
import torch
from torch import nn

from controlgs_adapter import ControlGS
from controlgs_adapter.backends.models.reference_model import NeuralGaussianModel
from controlgs_adapter.errors import TargetError


def _model() -> NeuralGaussianModel:
    torch.manual_seed(0)
    return NeuralGaussianModel(6, feat_dim=8, n_offsets=2)


def _snapshot(model: nn.Module) -> dict[str, object]:
    return {"hooks": [(name, len(m._forward_hooks), len(m._forward_pre_hooks)) for name, m in model.named_modules()],
            "modules": {name: id(m) for name, m in model.named_modules(remove_duplicate=False)},
            "grad": [(name, p.requires_grad) for name, p in model.named_parameters(remove_duplicate=False)],
            "state": {k: v.clone() for k, v in model.state_dict().items()}}


def _same(a: dict[str, object], b: dict[str, object]) -> bool:
    sa, sb = a["state"], b["state"]
    assert isinstance(sa, dict) and isinstance(sb, dict)
    return (all(a[k] == b[k] for k in ("hooks", "modules", "grad")) and sa.keys() == sb.keys()
            and all(torch.equal(sa[k], sb[k]) for k in sa))


@pytest.mark.parametrize("targets", [None, ("mlp_opacity", "mlp_cov"), ("mlp_color", "mlp_cov", "mlp_opacity")])
def test_targets_sharing_a_first_layer_are_refused_and_nothing_changes(targets: tuple[str, ...] | None) -> None:
    model = _model()
    model.mlp_cov[0] = model.mlp_opacity[0]  # one Linear in both decoders
    before = _snapshot(model)
    with pytest.raises(TargetError, match=r"targets '(mlp_opacity|mlp_cov)' and '(mlp_cov|mlp_opacity)' share one first "
                                          r"layer \('mlp_\w+\.0' is 'mlp_\w+\.0'\)"):
        ControlGS.wrap(model, targets=targets)
    assert _same(before, _snapshot(model))
    assert ControlGS.attached(model) is None
    cgs = ControlGS.wrap(model, targets=("mlp_opacity", "mlp_color"))  # one of them: wraps, one hook on the shared layer
    assert len(model.mlp_cov[0]._forward_hooks) + len(model.mlp_cov[0]._forward_pre_hooks) == 1
    cgs.unwrap()
    assert _same(before, _snapshot(model))


def test_one_decoder_under_two_names_is_refused() -> None:
    model = _model()
    model.mlp_color = model.mlp_opacity  # an alias: same first layer (and widths)
    before = _snapshot(model)
    with pytest.raises(TargetError, match=r"targets 'mlp_opacity' and 'mlp_color' share one first layer"):
        ControlGS.wrap(model, targets=("mlp_opacity", "mlp_color"))
    assert _same(before, _snapshot(model))
    assert ControlGS.attached(model) is None


def test_decoders_with_tied_weights_but_their_own_layers_wrap() -> None:
    model = _model()
    model.mlp_cov[0].weight = model.mlp_opacity[0].weight  # two Linear modules, one weight: one hook each, not doubled
    cgs = ControlGS.wrap(model, targets=("mlp_opacity", "mlp_cov"))
    assert [len(m[0]._forward_hooks) + len(m[0]._forward_pre_hooks) for m in (model.mlp_opacity, model.mlp_cov)] == [1, 1]
    cgs.unwrap()


import dataclasses
import json
import math
import types
import warnings
from pathlib import Path
from typing import Any, Callable

from helpers.adapter_files import rewrite, trained
from helpers.contextgs_files import PAD, A, K, _arrays, _decoders, _write_dir
from helpers.contextgs_files import _model as _model_2
from helpers.family_checks import outputs as outputs_2
from helpers.hac_files import VOXEL
from helpers.hac_files import A as A_2
from helpers.hac_files import _arrays as _arrays_2
from helpers.hac_files import _decoders as _decoders_2
from helpers.rawfiles import write_raw
from helpers.scaffold_oracle import camera_looking_down_z, make_raw_model, write_scaffold_dir_by_hand
from helpers.scaffold_standin import ScaffoldStandIn, make_camera, script_decoders
from helpers.scene_writers import write_blender, write_colmap, write_instant_ngp
from hypothesis import given, settings
from hypothesis import strategies as st
from safetensors.torch import save_file

from controlgs_adapter import RuntimeState, __version__
from controlgs_adapter.backends import load_model_dir
from controlgs_adapter.backends.contextgs import ContextGSBackend, load_contextgs_dir
from controlgs_adapter.backends.hac import HACModel
from controlgs_adapter.backends.scaffold_gs import ScaffoldGSBackend
from controlgs_adapter.backends.scaffold_io import load_scaffold_dir
from controlgs_adapter.cli import main
from controlgs_adapter.controlgs import ADAPTER_FORMAT_VERSION, ADAPTER_KIND, DEFAULT_ADAPTER, DEFAULT_MODULES, _backbone_tensors
from controlgs_adapter.downstream.pipeline import Pipeline
from controlgs_adapter.downstream.placement import to_display
from controlgs_adapter.errors import (
    ControlGSError,
    FileFormatError,
    FileWriteError,
    IncompatibleAdapterError,
    InjectionMissedError,
    InputValueError,
    LifecycleError,
    NoMatchingBackendError,
    NonFiniteError,
    ShapeError,
)
from controlgs_adapter.evaluation import IDEAL, condition_response, evaluate_grid, side_by_side
from controlgs_adapter.formats.adapter import read_spec
from controlgs_adapter.formats.safetensors import load_tensors, read_header, save_tensors
from controlgs_adapter.metrics import ssim
from controlgs_adapter.plugins import _describe
from controlgs_adapter.rendering.protocol import FunctionRenderer, render_view
from controlgs_adapter.scene import builtin_backbone_dir, load_builtin_scene
from controlgs_adapter.state import Camera
from controlgs_adapter.training import DEFAULT_EFFECTS

pytest.importorskip("skimage")

pytest.importorskip("matplotlib")



STATE = RuntimeState(downsample=5.0, power_saving=0.55)


def conditioned_outputs(cgs, model, cam, x):
    with torch.no_grad(), cgs.conditioned(STATE, camera=cam):
        return model.decode(x)


@pytest.fixture()
def saved(tmp_path):
    model = ScaffoldStandIn(30, seed=0)
    cgs = trained(model)
    path = cgs.save(tmp_path / "a.safetensors")
    cgs.unwrap()
    return path


def _load_error(path, model) -> str:
    with pytest.raises(IncompatibleAdapterError) as e:
        ControlGS.load(path, model)
    return str(e.value)


@pytest.mark.parametrize("kind", ["eager", "script"])
def test_round_trip_reproduces_outputs_exactly(tmp_path, kind):
    model, cam = ScaffoldStandIn(30), make_camera()
    if kind == "script":
        script_decoders(model)
    x = model.decoder_input(cam.center)
    cgs = trained(model, modules=("lens", "display", "foveation"), cond_dim=4, endpoints={"lens": (0.2, 1.1)})
    want = conditioned_outputs(cgs, model, cam, x)
    path = cgs.save(tmp_path / "a.controlgs.safetensors")
    cgs.unwrap()
    loaded = ControlGS.load(path, model)
    got = conditioned_outputs(loaded, model, cam, x)
    assert all(torch.equal(want[k], got[k]) for k in want)
    assert loaded.modules == ("lens", "display", "foveation") and loaded.injector.cond_dim == 4
    assert (loaded.schedules["lens"].lo, loaded.schedules["lens"].hi) == (0.2, 1.1)
    assert [t.from_torchscript for t in loaded.targets] == [kind == "script"] * 3


def test_header_describes_the_adapter(tmp_path):
    model = ScaffoldStandIn(30)
    cgs = trained(model, state_blind=True)
    path = cgs.save(tmp_path / "a.safetensors")
    h = read_header(path, kind=ADAPTER_KIND, max_version=ADAPTER_FORMAT_VERSION)
    assert h["format_version"] == ADAPTER_FORMAT_VERSION and h["library_version"] == __version__
    assert h["backend"] == "scaffold_gs" and h["modules"] == ["lens", "resample", "display"] and h["cond_dim"] == 8
    assert h["schedules"]["resample"] == {"class": "ResampleSchedule", "per_anchor": False, "lo": 0.0, "hi": 3.0}
    assert h["state_blind"] is True and h["num_anchors"] == 30 and h["rows_per_anchor"] == 1
    assert h["targets"][0] == {"decoder": "mlp_opacity", "fc1": "mlp_opacity.0", "in_features": 35, "out_features": 32}
    assert h["fingerprint"] == cgs.backend.fingerprint(model) and h["condition_dtype"] == "float32"
    cgs.unwrap()
    assert ControlGS.load(path, model).state_blind


def test_fp16_storage_halves_conditions_and_stays_close(tmp_path):
    model, cam = ScaffoldStandIn(200), make_camera()
    x = model.decoder_input(cam.center)
    cgs = trained(model)
    with torch.no_grad():  # trained conditions are small: keep them in a realistic range
        cgs.injector.conditions.mul_(0.1)
    want = conditioned_outputs(cgs, model, cam, x)
    full = cgs.save(tmp_path / "f32.safetensors")
    half = cgs.save(tmp_path / "f16.safetensors", dtype=torch.float16)
    tensors, header = load_tensors(half, kind=ADAPTER_KIND, max_version=ADAPTER_FORMAT_VERSION)
    assert header["condition_dtype"] == "float16" and tensors["conditions"].dtype == torch.float16
    assert tensors["projections.lens.d32.weight"].dtype == torch.float32
    saved_bytes = 3 * 200 * 8 * 2
    assert abs(full.stat().st_size - half.stat().st_size - saved_bytes) <= 16  # header padding
    expected_conditions = cgs.injector.conditions.detach().half().float()
    cgs.unwrap()
    loaded = ControlGS.load(half, model)
    assert torch.equal(loaded.injector.conditions.detach(), expected_conditions)
    assert loaded.injector.dtype == torch.float32
    got = conditioned_outputs(loaded, model, cam, x)
    err = max(float((want[k] - got[k]).abs().max()) for k in want)
    assert 0 < err < 1e-3
    with pytest.raises(Exception, match="dtype"):
        loaded.save(tmp_path / "bad.safetensors", dtype=torch.int8)


def test_other_anchor_count_and_widths_are_each_named(saved):
    msg = _load_error(saved, ScaffoldStandIn(31, feat_dim=16))
    assert "anchor count: the adapter has 30 anchors, the model 31" in msg
    for d in ("mlp_opacity", "mlp_cov", "mlp_color"):
        assert f"target '{d}': the adapter was made for Linear(35 -> 32), the model has Linear(19 -> 16)" in msg
    assert "backbone fingerprint" in msg


def test_other_backbone_weights_is_a_fingerprint_mismatch_only(saved):
    other = ScaffoldStandIn(30, seed=1)
    msg = _load_error(saved, other)
    assert "backbone fingerprint" in msg and "anchor count" not in msg and "target" not in msg
    assert not any(getattr(other, d)[0]._forward_hooks for d in ("mlp_opacity", "mlp_cov", "mlp_color"))


def test_other_backend_is_named(saved):
    rewrite(saved, {"backend": "octree_gs"})
    msg = _load_error(saved, ScaffoldStandIn(30, seed=0))
    assert "'octree_gs'" in msg and "recognised by scaffold_gs" in msg
    rewrite(saved, {"backend": "no_such_family"})
    assert "'no_such_family', which is not registered" in _load_error(saved, ScaffoldStandIn(30, seed=0))


def test_missing_unexpected_and_misshapen_tensors_are_listed_together(saved):
    rewrite(saved, tensor_changes={"extra.bias": torch.zeros(3), "conditions": torch.zeros(30, 3, 7)},
             drop=("projections.display.d32.weight",))
    msg = _load_error(saved, ScaffoldStandIn(30, seed=0))
    assert "missing from the file: ['projections.display.d32.weight']" in msg
    assert "unexpected tensors in the file: ['extra.bias']" in msg
    assert "tensor 'conditions': shape [30, 3, 7], expected [30, 3, 8]" in msg


def test_non_finite_tensor_is_refused(saved):
    bad = torch.zeros(30, 3, 8)
    bad[3, 1, 2] = float("nan")
    rewrite(saved, tensor_changes={"conditions": bad})
    assert "'conditions': contains NaN/Inf" in _load_error(saved, ScaffoldStandIn(30, seed=0))


def test_truncated_foreign_and_other_kind_files(saved, tmp_path):
    model = ScaffoldStandIn(30, seed=0)
    data = saved.read_bytes()
    truncated = tmp_path / "truncated.safetensors"
    truncated.write_bytes(data[: len(data) // 2])
    foreign = tmp_path / "foreign.safetensors"
    save_file({"w": torch.zeros(2)}, str(foreign))
    junk = tmp_path / "junk.safetensors"
    junk.write_bytes(b"\x00\x01 not safetensors at all")
    other_kind = tmp_path / "bank.safetensors"
    save_tensors(other_kind, {"psf": torch.zeros(2)}, {}, kind="psf_bank", format_version=1)
    newer = tmp_path / "newer.safetensors"
    save_tensors(newer, {}, {}, kind=ADAPTER_KIND, format_version=ADAPTER_FORMAT_VERSION + 1)
    for path, words in [(truncated, "truncated"), (foreign, "not written by controlgs-adapter"), (junk, "truncated or foreign"),
                        (other_kind, "holds a 'psf_bank'"), (newer, "newer"), (tmp_path / "none.safetensors", "no such file")]:
        with pytest.raises(FileFormatError, match=words):
            ControlGS.load(path, model)
    assert not model.mlp_opacity[0]._forward_hooks


def test_malformed_header_is_a_file_format_error(saved):
    rewrite(saved, {"targets": "mlp_opacity", "num_anchors": "30"})
    with pytest.raises(FileFormatError, match=r"\['targets', 'num_anchors'\]|\['num_anchors', 'targets'\]"):
        ControlGS.load(saved, ScaffoldStandIn(30, seed=0))
    rewrite(saved, {"targets": [{"decoder": "mlp_opacity"}], "num_anchors": 30})
    with pytest.raises(FileFormatError, match=r"targets\[0\]"):
        ControlGS.load(saved, ScaffoldStandIn(30, seed=0))


@pytest.mark.parametrize("missing", ["lo", "hi"])
def test_schedule_without_an_endpoint_is_a_file_format_error(saved, missing):
    """Each module's schedule needs both endpoints: a header without one is named, before any wrap."""
    schedules = read_spec(saved)["schedules"]
    module = sorted(schedules)[0]
    rewrite(saved, {"schedules": {**schedules, module: {k: v for k, v in schedules[module].items() if k != missing}}})
    model = ScaffoldStandIn(30, seed=0)
    with pytest.raises(FileFormatError, match=rf"malformed field\(s\) \['schedules\.{module}'\]"):
        ControlGS.load(saved, model)
    assert not model.mlp_opacity[0]._forward_hooks


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


def test_adapter_maps_between_live_padded_model_and_loaded_folder(tmp_path):
    """An adapter trained on the live (zero-padded) decoded model loads onto the stand-in of its
    folder (which drops invalid anchors; source_index maps the rows) and back, with equal outputs."""
    from controlgs_adapter import RuntimeState
    from controlgs_adapter.controlgs import ControlGS
    from controlgs_adapter.errors import IncompatibleAdapterError

    arr, decs = _arrays(7, decoded=True), _decoders(7)
    arr["mask"][3] = 0.0  # an invalid anchor among the valid ones
    root = _write_dir(tmp_path / "scene", arr, decs)
    live, loaded = _model_2(arr, decs, decoded=True), load_contextgs_dir(root)
    rows = [i for i in range(A - PAD) if i != 3]
    assert loaded.source_index.tolist() == rows
    cam, state = torch.tensor([0.0, 0.5, -6.0]), RuntimeState(downsample=4, power_saving=0.4)
    cgs = ControlGS.wrap(live, modules=("resample", "display"), cond_dim=4)
    with torch.no_grad():
        cgs.injector.conditions.normal_(generator=torch.Generator().manual_seed(0))
    cgs.save(tmp_path / "live.safetensors")
    pick = torch.arange(0, len(rows), 2)
    with cgs.conditioned(state, anchor_ids=loaded.source_index[pick]):
        want = outputs_2(live, live.decoder_inputs(cam, loaded.source_index[pick]))
    trained = cgs.injector.conditions.detach().clone()
    cgs.unwrap()
    on_loaded = ControlGS.load(tmp_path / "live.safetensors", loaded)
    assert torch.equal(on_loaded.injector.conditions.detach(), trained[loaded.source_index])
    with on_loaded.conditioned(state, anchor_ids=pick):
        got = outputs_2(loaded, loaded.decoder_inputs(cam, pick))
    for p in want:
        assert torch.equal(got[p], want[p]), p
    on_loaded.save(tmp_path / "loaded.safetensors")
    on_loaded.unwrap()
    back = ControlGS.load(tmp_path / "loaded.safetensors", live)
    assert torch.equal(back.injector.conditions.detach()[rows], trained[rows])
    assert not back.injector.conditions.detach()[[3, *range(A - PAD, A)]].any()  # invalid rows stay at zero
    back.unwrap()
    other = load_contextgs_dir(_write_dir(tmp_path / "other", _arrays(8, decoded=True), decs))
    with pytest.raises(IncompatibleAdapterError, match="anchor count"):
        ControlGS.load(tmp_path / "live.safetensors", other)
    # another scene with the same counts (valid anchors included) is no reason to scatter the rows onto it
    arr8 = _arrays(8, decoded=True)
    arr8["mask"][3] = 0.0
    live8 = _model_2(arr8, decs, decoded=True)
    assert int(ContextGSBackend().valid_anchors(live8).sum()) == len(rows)
    with pytest.raises(IncompatibleAdapterError, match="anchor count"):
        ControlGS.load(tmp_path / "loaded.safetensors", live8)


def _model_3(arr, decs, *, decoded: bool, variant: str = "hac++") -> HACModel:
    return HACModel(voxel_size=VOXEL, variant=variant, decoded_version=decoded, anchor=torch.from_numpy(arr["anchor"]),
                    offset=torch.from_numpy(arr["offset"]), mask=torch.from_numpy(arr["mask"])[:, :, None],
                    anchor_feat=torch.from_numpy(arr["feat"]), scaling=torch.from_numpy(arr["scale"]), **decs)


def test_invalid_anchor_condition_rows_get_no_gradient():
    """An anchor with every offset masked off reaches the decoders but emits no Gaussian, so its
    condition row receives no gradient (it stays inert at zero), while valid anchors' rows do."""
    from helpers.family_checks import STATE, make_camera

    from controlgs_adapter.controlgs import ControlGS

    arr = _arrays_2(6, decoded=False, mask_cols=K + 1, invalid=(2,))
    model = _model_3(arr, _decoders_2(6), decoded=False)
    cam = make_camera()
    cgs = ControlGS.wrap(model, modules=("display",), cond_dim=4)
    ids = torch.tensor([0, 1, 2, 3])
    with cgs.conditioned(STATE, anchor_ids=ids):
        g = model.decode(cam, torch.isin(torch.arange(A_2), ids))
    (g.colors.sum() + g.opacities.sum() + g.scales.sum()).backward()
    grad = cgs.injector.conditions.grad[:, 0]  # [A, N] of the display module
    assert bool((grad[2] == 0).all()) and 2 not in g.anchor_of.tolist()
    assert all(bool(grad[a].abs().sum() > 0) for a in (0, 1, 3))
    assert bool((grad[4:] == 0).all())  # anchors not in the view
    cgs.unwrap()


def _raises(fn: Callable[[], Any], error: type[BaseException] | tuple[type[BaseException], ...], *names: str) -> str:
    """Call ``fn``; it must raise ``error`` (a ControlGSError) whose message holds every one of ``names``."""
    with pytest.raises(error) as info:
        fn()
    assert isinstance(info.value, ControlGSError), type(info.value)
    msg = str(info.value)
    for n in names:
        assert n in msg, f"{n!r} not in {msg!r}"
    return msg


# ============================================================================ API: adapter wrap / save / load
@pytest.fixture
def cgs():
    c = ControlGS.wrap(ScaffoldStandIn(30, seed=0))
    yield c
    if c._wrapped:
        c.unwrap()


def _nan_conditions(c: ControlGS) -> None:
    with torch.no_grad():
        c.injector.conditions[0, 0, 0] = math.nan


def _huge_conditions(c: ControlGS) -> None:
    with torch.no_grad():
        c.injector.conditions[0, 0, 0] = 1e6


ADAPTER_CASES = [
    ("save None", lambda c, d: c.save(None), InputValueError, "path"),
    ("save 123", lambda c, d: c.save(123), InputValueError, "path"),
    ("save onto a folder", lambda c, d: c.save(d), InputValueError, "is a folder"),
    ("save under a file", lambda c, d: c.save(d / "f.txt" / "a.safetensors"), FileWriteError, "f.txt"),
    ("save dtype", lambda c, d: c.save(d / "a.safetensors", dtype=torch.int8), InputValueError, "dtype"),
    ("save NaN", lambda c, d: (_nan_conditions(c), c.save(d / "a.safetensors")), NonFiniteError, "conditions"),
    ("save fp16 overflow", lambda c, d: (_huge_conditions(c), c.save(d / "a.safetensors", dtype=torch.float16)),
     NonFiniteError, "float16"),
    ("load None", lambda c, d: ControlGS.load(None, ScaffoldStandIn(30, seed=0)), InputValueError, "path"),
    ("load a folder", lambda c, d: ControlGS.load(d, ScaffoldStandIn(30, seed=0)), FileFormatError, "no such file"),
    ("load missing", lambda c, d: ControlGS.load(d / "none.safetensors", ScaffoldStandIn(30, seed=0)), FileFormatError,
     "none.safetensors"),
    ("conditioned modules=5", lambda c, d: c.conditioned(RuntimeState(), modules=5).__enter__(), InputValueError, "modules"),
    ("conditioned modules=['nope']", lambda c, d: c.conditioned(RuntimeState(), modules=["nope"]).__enter__(),
     InputValueError, "nope"),
    ("conditioned modules='lns'", lambda c, d: c.conditioned(RuntimeState(), modules="lns").__enter__(),
     InputValueError, "lns"),
    ("conditioned state=None", lambda c, d: c.conditioned(None).__enter__(), InputValueError, "state"),
    ("wrap modules='lens'", lambda c, d: ControlGS.wrap(ScaffoldStandIn(30, seed=1), modules="lens"), InputValueError,
     "modules"),
]


HEADER_CASES = [
    ("format_version true", {"format_version": True}, "format_version"),
    ("format_version '1'", {"format_version": "1"}, "format_version"),
    ("format_version 0", {"format_version": 0}, "format_version"),
    ("format_version 1.0", {"format_version": 1.0}, "format_version"),
    ("format_version 99", {"format_version": 99}, "format_version"),
    ("header a list", {"raw_header": "[1, 2]"}, "JSON object"),
    ("header not JSON", {"raw_header": "{oops"}, "corrupt"),
    ("header deep JSON", {"raw_header": "[" * 100000 + "]" * 100000}, "corrupt"),
    ("other kind", {"kind": "psf_bank"}, "psf_bank"),
]


@pytest.mark.parametrize("call, error, name", [c[1:] for c in ADAPTER_CASES], ids=[c[0] for c in ADAPTER_CASES])
def test_adapter(cgs, tmp_path, call, error, name):
    (tmp_path / "f.txt").write_text("x")
    _raises(lambda: call(cgs, tmp_path), error, name)


def test_conditioned_takes_one_module_name_as_one_module(cgs):
    # "display" is one module, not the letters d, i, s, ...; nothing renders here, so the block warns
    with pytest.warns(RuntimeWarning, match="no wrapped decoder ran inside this conditioned block"):
        with cgs.conditioned(RuntimeState(power_saving=0.4), camera=make_camera(), modules="display"):
            assert list(cgs.injector._ctx.strengths) == ["display"]


@pytest.mark.parametrize("kw, name", [c[1:] for c in HEADER_CASES], ids=[c[0] for c in HEADER_CASES])
def test_file_headers(tmp_path, kw, name):
    p = write_raw(tmp_path / "f.safetensors", {"w": torch.zeros(2)}, {}, **{"kind": ADAPTER_KIND, **kw})
    _raises(lambda: load_tensors(p, kind=ADAPTER_KIND, max_version=1), FileFormatError, "f.safetensors", name)


MODEL = builtin_backbone_dir("ar")


# cheap downstream path (the PSF optics cost ~0.5 s per image whatever its size)
FAST = ["--effects", "resample,display", "--no-progress", "--checkpoint-every", "0"]


def _capture(size: int = 32, crop: tuple[int, int] | None = None) -> tuple[list[Camera], list[torch.Tensor]]:
    """8 views of the built-in scene (view 0 is the test view in every format); ``crop = (w, h)``
    cuts a centred window out of each image with matching intrinsics."""
    scene = load_builtin_scene("ar", size, views=8, test_every=8, samples=1)
    cams = scene.test_cameras + scene.train_cameras
    images = list(torch.cat([scene.test_images, scene.train_images]))
    if crop is None:
        return cams, images
    w, h = crop
    x0, y0 = (size - w) // 2, (size - h) // 2
    out = []
    for c in cams:
        k = c.intrinsics.clone()
        k[0, 2] -= x0
        k[1, 2] -= y0
        out.append(Camera(c.world_to_camera, k, w, h))
    return out, [img[:, y0:y0 + h, x0:x0 + w].contiguous() for img in images]


def _train_eval(tmp_path, data, name: str, *extra: str) -> dict:
    run, report = tmp_path / f"run-{name}", tmp_path / f"report-{name}"
    assert main(["train", "--model", str(MODEL), "--data", str(data), "--out", str(run), "--iterations", "3",
                 "--no-ablations", *FAST, *extra]) == 0
    record = json.loads((run / "run.json").read_text())
    assert record["family"] == "scaffold_gs" and record["iterations"] == 3 and record["effects"] == ["display", "resample"]
    assert (record["seeds"], record["seed"], record["holdout"]) == (1, 0, 8)  # one seed, the defaults
    assert main(["eval", "--run", str(run), "--out", str(report), "--test-views", "1", "--no-progress"]) == 0
    for f in ("results.json", "report.md", "heatmap.png", "comparison.png", "condition_response.png"):
        assert (report / f).is_file() and (report / f).stat().st_size > 0, f
    cgs = ControlGS.load(run / "controlgs.controlgs.safetensors", load_model_dir(MODEL))
    assert set(cgs.modules) == {"resample", "display"}
    cgs.unwrap()
    return json.loads((report / "results.json").read_text())


def test_three_formats_train_eval_and_agree(tmp_path, capsys):
    cams, images = _capture()
    folders = {"colmap": write_colmap(tmp_path / "colmap", cams, images),
               "blender": write_blender(tmp_path / "blender", cams, images, test=[0]),
               "instant_ngp": write_instant_ngp(tmp_path / "ngp", cams, images)}
    results = {fmt: _train_eval(tmp_path, path, fmt, "--resolution", "32") for fmt, path in folders.items()}
    out = capsys.readouterr().out
    assert out.count("scene check: ") == 3 and "anchors are in view of 8/8 cameras" in out
    ref = results["colmap"]
    assert ref["info"]["test_sizes"] == ["32x32"] and set(ref["methods"]) == {"no_ss", "ss", "ideal", "controlgs"}
    for fmt, r in results.items():
        assert r["info"]["test_views"] == 1, fmt
        for m, metrics in ref["methods"].items():
            for k, v in metrics.items():
                assert r["methods"][m][k]["mean"] == pytest.approx(v["mean"], abs=1e-6), (fmt, m, k)


def test_non_square_capture(tmp_path):
    cams, images = _capture(48, crop=(48, 28))
    data = write_instant_ngp(tmp_path / "ngp", cams, images)
    r = _train_eval(tmp_path, data, "wide")
    assert r["info"]["test_sizes"] == ["48x28"]
    assert all(torch.isfinite(torch.tensor(m["psnr"]["grid"])).all() for m in r["methods"].values())


FULL = RuntimeState(downsample=8.0, power_saving=0.8 - 1e-9)


def make_model(kind: str, **kw) -> ScaffoldStandIn:
    model = ScaffoldStandIn(**kw)
    return script_decoders(model) if kind == "script" else model


def randomise(cgs: ControlGS, seed: int = 1) -> None:
    g = torch.Generator().manual_seed(seed)
    with torch.no_grad():
        for p in cgs.trainable_parameters():
            p.copy_(torch.randn(p.shape, generator=g, dtype=p.dtype))


def outputs_4(model, x):
    with torch.no_grad():
        return model.decode(x)


def assert_equal_outputs(a, b):
    for k in a:
        assert torch.equal(a[k], b[k]), k


def _pinhole_screen(points: torch.Tensor, cam) -> torch.Tensor:
    """Independent float64 projection to normalised screen coordinates."""
    p = points.double() @ cam.world_to_camera[:3, :3].double().T + cam.world_to_camera[:3, 3].double()
    k = cam.intrinsics.double()
    u = k[0, 0] * p[:, 0] / p[:, 2] + k[0, 2]
    v = k[1, 1] * p[:, 1] / p[:, 2] + k[1, 2]
    return torch.stack([2 * u / cam.width - 1, 2 * v / cam.height - 1], dim=1)


def _snapshot_2(model):
    return {d: (getattr(model, d), [p.requires_grad for p in getattr(model, d).parameters()]) for d in DECODERS}


@pytest.mark.parametrize("kind", ["eager", "script"])
def test_bit_identical_at_init_inside_and_outside_the_block(kind):
    model, cam = make_model(kind), make_camera()
    x = model.decoder_input(cam.center)
    ref = outputs_4(model, x)
    cgs = ControlGS.wrap(model)
    assert_equal_outputs(ref, outputs_4(model, x))
    with cgs.conditioned(FULL, camera=cam):
        assert_equal_outputs(ref, outputs_4(model, x))


@pytest.mark.parametrize("kind", ["eager", "script"])
def test_bit_identical_when_every_strength_is_zero(kind):
    model, cam = make_model(kind), make_camera()
    x = model.decoder_input(cam.center)
    ref = outputs_4(model, x)
    # lens endpoints beyond every anchor's radius: lambda_lens = 0; d = 1, rho = 0: the others are 0
    cgs = ControlGS.wrap(model, endpoints={"lens": (5.0, 6.0)})
    randomise(cgs)
    with cgs.conditioned(RuntimeState(downsample=1.0, power_saving=0.0), camera=cam):
        # shared strengths of zero are not computed; a per-anchor one stays (testing it would sync the device)
        assert list(cgs.injector.context.strengths) == ["lens"]
        assert not bool(cgs.injector.context.strengths["lens"].any())
        assert_equal_outputs(ref, outputs_4(model, x))
    assert_equal_outputs(ref, outputs_4(model, x))  # outside the block after a randomised adapter


def test_only_rows_with_positive_strength_change():
    model, cam = make_model("eager", num_anchors=60), make_camera()
    x = model.decoder_input(cam.center)
    ref = outputs_4(model, x)
    cgs = ControlGS.wrap(model, modules=("lens",), endpoints={"lens": (0.3, 1.0)})
    randomise(cgs)
    lam = cgs.strengths(FULL, cam)["lens"]
    on = lam > 0
    assert 0 < int(on.sum()) < on.numel()
    with cgs.conditioned(FULL, camera=cam):
        out = outputs_4(model, x)
    for k in out:
        assert torch.equal(out[k][~on], ref[k][~on]), k
        # every changed row differs somewhere (tanh/sigmoid outputs are not saturated here)
        assert bool((out[k][on] != ref[k][on]).any(dim=1).all()), k


@pytest.mark.parametrize("kind", ["eager", "script"])
def test_injection_matches_eq9_in_float64(kind):
    """FC1 output + sum_m lambda_m * A_m(C_m) through the rest of the decoder, computed by hand."""
    model, cam = make_model(kind, num_anchors=30, dtype=torch.float64), make_camera(dtype=torch.float64)
    eager = {d: (getattr(model, d) if kind == "eager" else None) for d in DECODERS}
    visible = torch.arange(30) % 3 != 1
    x = model.decoder_input(cam.center, visible)
    state = RuntimeState(downsample=2.5, power_saving=0.3)
    cgs = ControlGS.wrap(model, endpoints={"lens": (0.1, 1.2)})
    randomise(cgs)
    eager = {d: getattr(model, d) for d in DECODERS}  # rebuilt eager decoders for the script variant
    ids = visible.nonzero().squeeze(1)
    on_display = torch.tensor([1.0, cam.height / cam.width], dtype=torch.float64)  # "fit" placement, landscape
    r = torch.linalg.vector_norm(_pinhole_screen(model._anchor.detach()[ids], cam) * on_display, dim=1)
    lam = {"lens": ((r - 0.1) / 1.1).clamp(0, 1), "resample": torch.full_like(r, math.log2(2.5) / 3),
           "display": torch.full_like(r, 0.3 / 0.8)}
    with cgs.conditioned(state, camera=cam, anchor_ids=visible):
        got = outputs_4(model, x)
    with torch.no_grad():
        for d, name in zip(DECODERS, ("opacity", "cov", "color")):
            seq = eager[d]
            h = x @ seq[0].weight.T + seq[0].bias
            for m, lm in lam.items():
                c = cgs.injector.condition(m).detach()[ids]
                a = cgs.injector.projections[m]["d32"].weight.detach()
                h = h + lm[:, None] * (c @ a.T)
            want = seq[1:](h)
            assert torch.allclose(got[name], want, rtol=0, atol=1e-12), d


def test_rows_per_anchor_groups_rows_by_anchor():
    class KRows(ScaffoldGSBackend):
        """Scaffold layout with 3 decoder rows per anchor (CompGS-like)."""

        name = "k_rows_test"

        def rows_per_anchor(self, model):
            return 3

    model, cam = make_model("eager", num_anchors=12), make_camera()
    ids = torch.tensor([7, 2, 9, 0])
    x = model.decoder_input(cam.center)[ids].repeat_interleave(3, dim=0)  # [12, 35]
    x = x + 0.01 * torch.randn_like(x)
    cgs = ControlGS.wrap(model, backend=KRows(), modules=("resample", "lens"))
    randomise(cgs)
    with cgs.conditioned(FULL, camera=cam, anchor_ids=ids):
        got = model.mlp_cov[0](x)
        with pytest.raises(ShapeError, match="4 anchor ids x 3 rows"):
            model.mlp_cov[0](x[:4])
    lam = cgs.strengths(FULL, cam, ids)
    inj = sum(lam[m][:, None] * (cgs.injector.condition(m)[ids] @ cgs.injector.projections[m]["d32"].weight.T)
              for m in ("resample", "lens"))
    want = nn.functional.linear(x, model.mlp_cov[0].weight, model.mlp_cov[0].bias) + inj.repeat_interleave(3, dim=0)
    assert torch.allclose(got, want.detach(), atol=1e-6)


def test_state_blind_injects_fully_at_the_neutral_state():
    model, cam = make_model("eager"), make_camera()
    x = model.decoder_input(cam.center)
    ref = outputs_4(model, x)
    cgs = ControlGS.wrap(model, state_blind=True)
    randomise(cgs)
    neutral = RuntimeState(downsample=1.0, power_saving=0.0)
    assert all(torch.equal(v, torch.ones_like(v)) for v in cgs.strengths(neutral, cam).values())
    with cgs.conditioned(neutral):  # no camera needed: the strength does not depend on the state
        blind = outputs_4(model, x)
    assert not torch.equal(blind["color"], ref["color"])


def test_modules_switched_off_in_a_block_are_not_injected():
    model, cam = make_model("eager"), make_camera()
    x = model.decoder_input(cam.center)
    full = ControlGS.wrap(model)
    randomise(full)
    with full.conditioned(FULL, camera=cam, modules=("display",)):
        assert list(full.injector.context.strengths) == ["display"]
        only_display = outputs_4(model, x)
    state = {k: v.detach().clone() for k, v in full.injector.state_dict().items()}
    full.unwrap()
    single = ControlGS.wrap(model, modules=("display",))
    single.injector.load_state_dict({"conditions": state["conditions"][:, 2:3],
                                     "projections.display.d32.weight": state["projections.display.d32.weight"]})
    with single.conditioned(FULL, camera=cam):
        assert_equal_outputs(only_display, outputs_4(model, x))
    with pytest.raises(InputValueError, match="not wrapped"):
        with single.conditioned(FULL, camera=cam, modules=("lens",)):
            pass


def test_gradients_reach_only_the_adapter_and_the_backbone_does_not_move():
    model, cam = make_model("eager"), make_camera()
    x = model.decoder_input(cam.center).detach()
    before = {d: {k: v.clone() for k, v in getattr(model, d).state_dict().items()} for d in DECODERS}
    anchors_before = model._anchor.detach().clone()
    cgs = ControlGS.wrap(model)
    with torch.no_grad():  # non-zero conditions so that projections get non-zero gradients too
        cgs.injector.conditions.normal_()
    opt = torch.optim.Adam(cgs.trainable_parameters(), lr=1e-2)
    with cgs.conditioned(FULL, camera=cam):
        loss = sum(v.square().mean() for v in model.decode(x).values())
    loss.backward()
    adapter = list(cgs.trainable_parameters())
    assert len(adapter) == 1 + 3  # the conditions [A, 3, N], three projections (one width)
    assert all(p.grad is not None and bool(p.grad.abs().sum() > 0) for p in adapter)
    backbone = [p for d in DECODERS for p in getattr(model, d).parameters()] + [model._anchor, model._anchor_feat]
    assert all(p.grad is None and not p.requires_grad for p in backbone)
    opt.step()
    for d in DECODERS:
        assert all(torch.equal(v, before[d][k]) for k, v in getattr(model, d).state_dict().items())
    assert torch.equal(model._anchor.detach(), anchors_before)


def test_adapter_gradients_match_finite_differences_float64():
    model, cam = make_model("eager", num_anchors=6, feat_dim=4, dtype=torch.float64), make_camera(dtype=torch.float64)
    x = model.decoder_input(cam.center).detach()
    cgs = ControlGS.wrap(model, cond_dim=2, endpoints={"lens": (0.0, 1.0)})
    randomise(cgs)
    state = RuntimeState(downsample=3.0, power_saving=0.5)
    w = torch.randn(6, 30, dtype=torch.float64)

    def loss():
        with cgs.conditioned(state, camera=cam):
            return (model.mlp_color(x) * w).sum()

    loss().backward()
    checked = 0
    for p in cgs.trainable_parameters():
        for i in torch.randperm(p.numel())[:4].tolist():
            flat = p.data.view(-1)
            old = float(flat[i])
            with torch.no_grad():
                flat[i] = old + 1e-6
                up = float(loss())
                flat[i] = old - 1e-6
                down = float(loss())
            flat[i] = old
            assert math.isclose(float(p.grad.view(-1)[i]), (up - down) / 2e-6, rel_tol=1e-5, abs_tol=1e-8)
            checked += 1
    assert checked == 4 * 4  # conditions + three projections


def test_an_optimizer_step_inside_one_block_is_seen_by_the_next_decode():
    model, cam = make_model("eager"), make_camera()
    x = model.decoder_input(cam.center).detach()
    cgs = ControlGS.wrap(model)
    randomise(cgs)
    opt = torch.optim.SGD(cgs.trainable_parameters(), lr=0.5)
    with cgs.conditioned(FULL, camera=cam):
        model.mlp_color(x).sum().backward()
        opt.step()
        after = model.mlp_color(x).detach()
    with cgs.conditioned(FULL, camera=cam):
        fresh = model.mlp_color(x).detach()
    assert torch.equal(after, fresh)


@pytest.mark.parametrize("kind", ["eager", "script"])
def test_unwrap_restores_objects_flags_and_outputs(kind):
    model, cam = make_model(kind, use_feat_bank=True), make_camera()
    x = model.decoder_input(cam.center)
    ref = outputs_4(model, x)
    objects = {d: getattr(model, d) for d in (*DECODERS, "mlp_feature_bank")}
    model._anchor_feat.requires_grad_(False)  # a mix of flags, restored as they were
    flags = {id(t): t.requires_grad for t in (model._anchor, model._anchor_feat, model._offset)}
    cgs = ControlGS.wrap(model)
    if kind == "script":
        assert all(getattr(model, d) is not objects[d] for d in DECODERS)
    assert getattr(model, "mlp_feature_bank") is objects["mlp_feature_bank"]  # not a default target
    randomise(cgs)
    fc1s = [getattr(model, d)[0] for d in DECODERS]
    assert cgs.unwrap() is model
    assert all(getattr(model, d) is objects[d] for d in objects)
    assert all(not f._forward_hooks for f in fc1s)
    assert {id(t): t.requires_grad for t in (model._anchor, model._anchor_feat, model._offset)} == flags
    assert_equal_outputs(ref, outputs_4(model, x))
    with pytest.raises(LifecycleError, match="unwrapped"):
        with cgs.conditioned(FULL, camera=cam):
            pass
    ControlGS.wrap(model).unwrap()  # can be wrapped again


def test_wrong_rows_ids_and_masks_raise():
    model, cam = make_model("eager", num_anchors=20), make_camera()
    x = model.decoder_input(cam.center)
    cgs = ControlGS.wrap(model)
    mask = torch.zeros(20, dtype=torch.bool)
    mask[:5] = True
    assert cgs.anchor_ids(torch.arange(20) % 3 == 1).tolist() == list(range(1, 20, 3))  # a mask's anchors, ascending
    with cgs.conditioned(FULL, camera=cam, anchor_ids=mask):
        model.decode(x[:5])
        with pytest.raises(ShapeError, match="called with 20 rows .* expects 5 rows"):
            model.decode(x)
        with pytest.raises(LifecycleError, match="nested"):
            with cgs.conditioned(FULL, camera=cam):
                pass
    with pytest.raises(ShapeError, match=r"anchor_ids mask must have size 20 .*got \[19\]"):
        with cgs.conditioned(FULL, camera=cam, anchor_ids=torch.ones(19, dtype=torch.bool)):
            pass
    with pytest.raises(InputValueError, match=r"\[0, 20\)"):
        with cgs.conditioned(FULL, camera=cam, anchor_ids=torch.tensor([3, 20])):
            pass
    with pytest.raises(InputValueError, match="integer or bool"):
        with cgs.conditioned(FULL, camera=cam, anchor_ids=torch.tensor([1.0])):
            pass
    with pytest.raises(InputValueError, match="camera"):
        with cgs.conditioned(FULL, anchor_ids=mask):  # lens needs the camera
            pass
    with pytest.raises(InputValueError, match="RuntimeState"):
        with cgs.conditioned({"downsample": 2}, camera=cam):
            pass
    assert cgs.injector.context is None  # failed entries leave nothing active
    model.decode(x)  # and outside a block any row count is fine


@pytest.mark.parametrize("kwargs, error, words", [
    (dict(targets=["mlp_opacity", "mlp_nope"]), TargetError, ["mlp_nope", "mlp_color"]),
    (dict(targets=["mlp_opacity", "mlp_opacity"]), TargetError, ["more than once"]),
    (dict(modules=("lens", "vignetting")), InputValueError, ["vignetting", "resample"]),
    (dict(modules=()), InputValueError, ["at least one"]),
    (dict(cond_dim=0), InputValueError, ["cond_dim"]),
    (dict(endpoints={"lens": (1.0, 1.0)}), InputValueError, ["lens", "differ"]),
    (dict(endpoints={"display": (0, 1)}, modules=("lens",)), InputValueError, ["display"]),
    (dict(backend="octree_family_that_is_not_there"), NoMatchingBackendError, ["scaffold_gs", "not registered"]),
])
@pytest.mark.parametrize("kind", ["eager", "script"])
def test_wrap_validates_everything_before_changing_the_model(kind, kwargs, error, words):
    model = make_model(kind)
    before = _snapshot_2(model)
    with pytest.raises(error) as e:
        ControlGS.wrap(model, **kwargs)
    for w in words:
        assert w in str(e.value)
    after = _snapshot_2(model)
    assert all(after[d][0] is before[d][0] and after[d][1] == before[d][1] for d in DECODERS)
    if kind == "eager":
        assert not any(getattr(model, d)[0]._forward_hooks for d in DECODERS)


def test_unsupported_torchscript_layer_in_the_last_target_leaves_the_others_untouched():
    model = make_model("script")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", DeprecationWarning)
        model.mlp_color = torch.jit.trace(nn.Sequential(nn.Linear(35, 32), nn.GELU(), nn.Linear(32, 30)), torch.randn(2, 35))
    before = _snapshot_2(model)
    with pytest.raises(TargetError) as e:
        ControlGS.wrap(model)
    assert "mlp_color" in str(e.value) and "GELU" in str(e.value)
    after = _snapshot_2(model)
    assert all(after[d][0] is before[d][0] for d in DECODERS)


def test_no_matching_backend_lists_what_each_backend_looks_for():
    class NotAModel:
        mlp_opacity = nn.Linear(3, 3)

    with pytest.raises(NoMatchingBackendError) as e:
        ControlGS.wrap(NotAModel())
    msg = str(e.value)
    assert "NotAModel" in msg and "scaffold_gs" in msg and "mlp_color" in msg


def test_wrapping_twice_is_refused_and_feature_bank_is_targetable():
    model = make_model("eager", use_feat_bank=True)
    cgs = ControlGS.wrap(model)
    with pytest.raises(LifecycleError, match=r"already carries an injector \(ControlGS\(backend='scaffold_gs'"):
        ControlGS.wrap(model)
    assert ControlGS.attached(model) is cgs
    ControlGS.attached(model).unwrap()
    assert ControlGS.attached(model) is None
    cgs = ControlGS.wrap(model, targets=["mlp_feature_bank", "mlp_color"])
    assert [(t.decoder, t.in_features, t.out_features) for t in cgs.targets] == [("mlp_feature_bank", 4, 32),
                                                                                ("mlp_color", 35, 32)]
    assert "mlp_feature_bank.0: Linear(4 -> 32)" in cgs.summary()
    cgs.unwrap()


def test_grid_invariants_zero_adapter_equals_ss(tmp_path):
    """An adapter at initialisation (zero conditions) is the backbone: its grid equals the
    SS-backbone's exactly; at d = 1 the no-SS render is the SS render."""
    from controlgs_adapter import ControlGS
    from controlgs_adapter.backends.models.reference_model import NeuralGaussianModel
    from controlgs_adapter.evaluation import evaluate_grid
    from controlgs_adapter.scene import load_builtin_scene

    scene = load_builtin_scene("ar", 16, views=4, test_every=4, samples=1)
    xyz, rgb = scene.points(0.3)
    with torch.random.fork_rng(devices=[]):  # decoder weights: a fixed draw whose Gaussians are visible
        torch.manual_seed(1)
        model = NeuralGaussianModel.from_points(xyz, rgb, feat_dim=8, n_offsets=2, voxel_size=0.4, color_fit_steps=10).eval()
        with torch.no_grad():
            model.mlp_opacity[2].bias.fill_(1.0)
    with torch.no_grad():
        assert float(model.render(scene.test_cameras[0]).alpha.mean()) > 0.05
    cgs = ControlGS.wrap(model, cond_dim=4)
    path = cgs.save(tmp_path / "zero.safetensors")
    cgs.unwrap()
    r = evaluate_grid(model, scene.views("test"), {"controlgs": path}, downsample=(1.0, 4.0),
                      power_saving=(0.0, 0.6), optics_mode="fast", extra_metrics=False, progress=False)
    for k in ("psnr", "ssim"):
        assert torch.equal(r.per_view["controlgs"][k], r.per_view["ss"][k])
        assert torch.equal(r.per_view["no_ss"][k][0], r.per_view["ss"][k][0])
        assert not torch.equal(r.per_view["no_ss"][k][1], r.per_view["ss"][k][1])


# ----------------------------------------------------------------------------- condition strengths
def test_lens_strength_follows_the_radial_distance_on_the_display():
    """16:9 camera: an anchor at the right edge's middle gets 1/sqrt 2, one at the top edge's middle
    (9/16) / sqrt 2; with placement "stretch" both get 1/sqrt 2."""
    cam = make_camera(width=64, height=36)
    fx, dist = float(cam.intrinsics[0, 0]), float(cam.world_to_camera[2, 3])
    model = ScaffoldStandIn(num_anchors=4, seed=0)
    with torch.no_grad():
        model._anchor.copy_(torch.tensor([[32 * dist / fx, 0.0, 0.0], [0.0, -18 * dist / fx, 0.0],
                                          [0.0, 0.0, 0.0], [-32 * dist / fx, 18 * dist / fx, 0.0]]))
    cgs = ControlGS.wrap(model, modules=("lens", "foveation"))
    try:
        lam = cgs.strengths(RuntimeState(gaze=(0.0, -1.0)), cam)
        r2 = math.sqrt(2)
        assert torch.allclose(lam["lens"], torch.tensor([1 / r2, 9 / 16 / r2, 0.0, math.hypot(1, 9 / 16) / r2]), atol=1e-6)
        # gaze at the top edge's middle, also placed on the display
        fov = (torch.tensor([math.hypot(1, 9 / 16), 0.0, 9 / 16, math.hypot(1, 9 / 8)]) / r2).clamp(max=1)
        assert torch.allclose(lam["foveation"], fov, atol=1e-6)
        square = make_camera(width=36, height=36)
        lam_sq = cgs.strengths(RuntimeState(), square)["lens"]
        xy = square.normalized_screen(model._anchor.detach())
        assert torch.equal(lam_sq, (xy.norm(dim=1) / r2).clamp(0, 1).float())
        cgs.placement = "stretch"
        assert torch.allclose(cgs.strengths(RuntimeState(), cam)["lens"][:2], torch.full((2,), 1 / r2), atol=1e-6)
    finally:
        cgs.unwrap()


def test_nested_conditioned_blocks_are_refused():
    model, cam = ScaffoldStandIn(), make_camera()
    cgs = ControlGS.wrap(model)
    try:
        with cgs.conditioned(RuntimeState(downsample=2.0), camera=cam):
            model.decode(model.decoder_input(cam.center))  # the outer block is used
            with pytest.raises(LifecycleError, match="already inside"):
                with cgs.conditioned(RuntimeState(), camera=cam):
                    pass
    finally:
        cgs.unwrap()


def test_no_grad_decode_then_grad_decode_in_one_block_has_a_graph():
    """The injection cached under no_grad must not be reused by a decode with grad enabled."""
    torch.manual_seed(0)
    model, cam = ScaffoldStandIn(), make_camera()
    cgs = ControlGS.wrap(model, modules=("resample",), cond_dim=4)
    with torch.no_grad():
        cgs.injector.conditions.normal_()
    x = model.decoder_input(cam.center)
    with cgs.conditioned(RuntimeState(downsample=4.0), camera=cam):
        with torch.no_grad():
            model.decode(x)
        loss = sum(y.sum() for y in model.decode(x).values())
    assert loss.requires_grad
    loss.backward()
    assert cgs.injector.conditions.grad is not None and cgs.injector.conditions.grad.abs().sum() > 0
    cgs.unwrap()


def test_strengths_reported_are_the_schedules_absolute_values():
    """lambda = log2(d) / 3 (resample), rho / 0.8 (display), |p| / sqrt(2) clamped (lens)."""
    model, cam = ScaffoldStandIn(), make_camera()
    cgs = ControlGS.wrap(model, cond_dim=4)
    lam = cgs.strengths(RuntimeState(downsample=2.0, power_saving=0.3), cam)
    assert torch.allclose(lam["resample"].double(), torch.full_like(lam["resample"].double(), 1 / 3), atol=1e-7)
    assert torch.allclose(lam["display"].double(), torch.full_like(lam["display"].double(), 0.375), atol=1e-7)

    p = to_display(cam.normalized_screen(model.get_anchor.detach()).double(), cam.height, cam.width, cgs.placement)
    want = (p.norm(dim=1) / math.sqrt(2)).clamp(0, 1)
    assert torch.allclose(lam["lens"].double(), want, atol=1e-6)
    assert 0 < float(want.min()) < float(want.max()) < 1
    cgs.unwrap()


STATE_2 = RuntimeState(downsample=2, power_saving=0.4)


def test_torchscript_decoders_are_replaced_on_the_users_object():
    """A plain-Python model with TorchScript decoders (a Scaffold-GS checkpoint): wrap puts hooked
    eager copies ON that object, so code holding the object (its renderer) sees the injection."""
    model = script_decoders(ScaffoldStandIn(num_anchors=30))
    originals = {k: getattr(model, k) for k in ("mlp_opacity", "mlp_cov", "mlp_color")}
    cam = make_camera()
    x = model.decoder_input(cam.center)
    before = model.decode(x)
    cgs = ControlGS.wrap(model, modules=("display",))
    with torch.no_grad():
        cgs.injector.conditions.normal_()
    for k, scripted in originals.items():
        assert isinstance(scripted, torch.jit.ScriptModule) and not isinstance(getattr(model, k), torch.jit.ScriptModule)
    renderer = FunctionRenderer(lambda m, c, v, bg: m.decode(m.decoder_input(c.center))["color"][:, :3].T.reshape(3, 3, 10))
    with torch.no_grad(), cgs.conditioned(STATE_2, cam):
        after = model.decode(x)
        assert cgs.injector.context.calls == {"mlp_opacity": 1, "mlp_cov": 1, "mlp_color": 1}
    assert not torch.equal(after["color"], before["color"])
    cam3 = make_camera(width=10, height=3)
    with torch.no_grad():
        image = render_view(cgs, model, cam3, STATE_2, renderer=renderer)
    assert image.shape == (3, 3, 10)
    cgs.unwrap()
    assert all(getattr(model, k) is v for k, v in originals.items())


def test_loaded_directory_is_wrappable_and_rows_map_to_visible_anchors(tmp_path):
    from controlgs_adapter import ControlGS
    from controlgs_adapter.state import RuntimeState

    raw = make_raw_model(30, 8, 3, seed=11)
    write_scaffold_dir_by_hand(tmp_path, raw)
    model = load_scaffold_dir(tmp_path)
    cam = camera_looking_down_z()
    visible = torch.arange(30) % 3 != 1
    before = model.decode(cam, visible)
    cgs = ControlGS.wrap(model, modules=("resample",))
    state = RuntimeState(downsample=8.0)
    with torch.no_grad(), cgs.conditioned(state, camera=cam, anchor_ids=visible):
        same = model.decode(cam, visible)  # conditions are zero at init: bit-identical
        cgs.injector.conditions[12].normal_()  # anchor 12 (visible) only
        moved = model.decode(cam, visible)
    for name in ("means", "scales", "rotations", "opacities", "colors"):
        assert torch.equal(getattr(same, name), getattr(before, name)), name
    # only anchor 12's rows change (the mask may drop/keep some of its Gaussians)
    keep_b, keep_m = before.anchor_of != 12, moved.anchor_of != 12
    assert torch.equal(before.colors[keep_b], moved.colors[keep_m])
    changed = (moved.neural_opacity - before.neural_opacity).reshape(-1, 3).abs().sum(1) > 0
    assert torch.equal(before.visible_ids[changed], torch.tensor([12]))
    cgs.unwrap()


states = st.builds(
    RuntimeState,
    downsample=st.floats(1.0, 64.0),  # beyond the supported 8: clamps
    power_saving=st.floats(0.0, 0.999),  # beyond the supported 0.8: clamps
    gaze=st.none() | st.tuples(st.floats(-1, 1), st.floats(-1, 1)),
)


def _clamp01(v: float) -> float:
    return min(max(v, 0.0), 1.0)


def _reference(state: RuntimeState, xy: tuple[float, float], e_lens=(0.0, math.sqrt(2)), e_fov=(0.0, math.sqrt(2))):
    """Eqs. 10-11 with plain Python floats."""
    r = math.hypot(*xy)
    ecc = 0.0 if state.gaze is None else math.hypot(xy[0] - state.gaze[0], xy[1] - state.gaze[1])
    return {
        "lens": _clamp01((r - e_lens[0]) / (e_lens[1] - e_lens[0])),
        "resample": _clamp01(math.log2(state.downsample) / 3.0),
        "display": _clamp01(state.power_saving / 0.8),
        "foveation": _clamp01((ecc - e_fov[0]) / (e_fov[1] - e_fov[0])),
    }


_model_4 = ScaffoldStandIn(num_anchors=25, seed=3)


@settings(max_examples=20, deadline=None)
@given(states, st.floats(0.0, 0.5), st.floats(0.6, 2.0), st.integers(0, 2**31 - 1))
def test_controlgs_strengths_project_each_anchor_with_the_camera(state, lo, hi, seed):
    cam = make_camera(width=40, height=30)
    cgs = ControlGS.wrap(_model_4, modules=("lens", "resample", "display", "foveation"),
                         endpoints={"lens": (lo, hi), "foveation": (lo, hi)})
    try:
        ids = torch.randperm(25, generator=torch.Generator().manual_seed(seed))[:10]
        got = cgs.strengths(state, cam, ids)
        # independent pinhole projection in float64
        pts = _model_4._anchor.detach().double()[ids]
        k = cam.intrinsics.double()
        z = pts[:, 2] + float(cam.world_to_camera[2, 3])
        u = k[0, 0] * pts[:, 0] / z + k[0, 2]
        v = k[1, 1] * pts[:, 1] / z + k[1, 2]
        xy = torch.stack([2 * u / cam.width - 1, 2 * v / cam.height - 1], dim=1)
        assert bool((xy.abs() > 1).any())  # some anchors are off screen
        # anchors and gaze on the display ("fit" placement: the 40 px width spans it, the height 30/40)
        xy = xy * torch.tensor([1.0, 30 / 40], dtype=torch.float64)
        if state.gaze is not None:
            state = RuntimeState(state.downsample, state.power_saving, (state.gaze[0], state.gaze[1] * 30 / 40))
        for i in range(len(ids)):
            want = _reference(state, (float(xy[i, 0]), float(xy[i, 1])), (lo, hi), (lo, hi))
            for m in want:
                assert math.isclose(float(got[m][i]), want[m], abs_tol=2e-6), (m, i)
    finally:
        cgs.unwrap()


def test_a_module_named_twice_is_refused():
    from controlgs_adapter.backends.models.reference_model import NeuralGaussianModel
    from controlgs_adapter.controlgs import ControlGS

    model = NeuralGaussianModel(5, feat_dim=8, n_offsets=2)
    with pytest.raises(InputValueError, match=r"\['display'\] more than once"):
        ControlGS.wrap(model, modules=("display", "resample", "display"), cond_dim=2)
    cgs = ControlGS.wrap(model, modules=("display", "resample"), cond_dim=2)  # each once: accepted
    cgs.unwrap()


def test_summary_parameter_counts_by_hand():
    """A = 7 anchors, 2 modules, N = 3: conditions 7 * 2 * 3 = 42; one FC1 width (D1 = F = 8) shared by
    the three decoders: projections 2 modules * 8 * 3 = 48; 90 in all (numbers shown to users)."""
    from controlgs_adapter.backends.models.reference_model import NeuralGaussianModel
    from controlgs_adapter.controlgs import ControlGS

    cgs = ControlGS.wrap(NeuralGaussianModel(7, feat_dim=8, n_offsets=2), modules=("display", "resample"), cond_dim=3)
    try:
        assert "  trainable: 90 parameters (conditions 42, projections 48)" in cgs.summary().splitlines()
        assert sum(p.numel() for p in cgs.trainable_parameters()) == 90
    finally:
        cgs.unwrap()


# ------------------------------------------------------------------------------ side_by_side scores (eye, gt)
def test_side_by_side_scores_against_the_unclamped_ground_truth(tiny, tmp_path):
    from controlgs_adapter.evaluation import side_by_side
    from controlgs_adapter.metrics import ssim

    scene, model = tiny
    views = scene.data.views("train", first=1)
    cgs = ControlGS.wrap(model, cond_dim=4)
    path = cgs.save(tmp_path / "a.controlgs.safetensors")
    cgs.unwrap()
    cam, gt = views[0]
    bright = gt + 0.5  # a reference brighter than a display shows: only the eye image is clamped to [0, 1]
    assert float(bright.max()) > 1.2
    out = side_by_side(model, path, cam, bright, settings=[(1.0, 0.0)], background=views.background,
                       effects={"lens": True, "resample": True, "display": True})
    for method, row in out["rows"].items():
        _, eye, p, q = row[0]
        assert float(eye.max()) <= 1.0
        mse = float((eye.double() - bright.double()).square().mean())  # float64 PSNR against the unclamped gt
        assert p == pytest.approx(10 * math.log10(1.0 / mse), abs=1e-9), method
        assert q == pytest.approx(float(ssim(eye.double(), bright.double())), abs=1e-9), method
        clamped = float((eye.double() - bright.double().clamp(0, 1)).square().mean())
        assert abs(10 * math.log10(1.0 / clamped) - p) > 0.1  # the clamped reference would score differently


# ------------------------------------------------------------------------------ ControlGS targets
def test_wrapped_targets_are_read_only_hashable_records():
    """``cgs.targets`` records what the wrapper attached to (``unwrap`` finds its hooks by them): a Target
    cannot be edited afterwards, and as a value it hashes like its equal."""
    cgs = ControlGS.wrap(ScaffoldStandIn(5, seed=1))
    try:
        first = cgs.targets[0]
        with pytest.raises(dataclasses.FrozenInstanceError):
            first.fc1 = "mlp_cov.0"  # type: ignore[misc]
        assert first.fc1 == "mlp_opacity.0"
        copy = dataclasses.replace(first)
        assert copy == first and hash(copy) == hash(first)
        assert len(set(cgs.targets)) == 3 and {first: "x"}[copy] == "x"
    finally:
        model = cgs.unwrap()
    assert all(not getattr(model, d)[0]._forward_hooks for d in ("mlp_opacity", "mlp_cov", "mlp_color"))


class _Picky(ScaffoldGSBackend):
    """Picky test backend: Scaffold layout with settable anchors and rows."""

    name = "picky"

    def __init__(self, rows=1, anchors=None):
        self.rows, self.anchors = rows, anchors

    def rows_per_anchor(self, model):
        return self.rows

    def num_anchors(self, model):
        return super().num_anchors(model) if self.anchors is None else self.anchors


class _FC1Elsewhere(ScaffoldGSBackend):
    """FC1-elsewhere test backend."""

    name = "fc1_elsewhere"

    def __init__(self, fc1):
        self.fc1 = fc1

    def first_linear_path(self, model, decoder_path):
        return self.fc1.format(decoder_path)


class _FailingHook(ScaffoldGSBackend):
    """Failing-hook test backend: the second make_hookable fails."""

    name = "failing_hook"

    def __init__(self):
        self.calls = 0

    def make_hookable(self, model, decoder_path):
        self.calls += 1
        if self.calls == 2:
            raise RuntimeError("hook failed")
        return super().make_hookable(model, decoder_path)


class _BadHookable(ScaffoldGSBackend):
    """Bad-hookable test backend: make_hookable installs another first layer."""

    name = "bad_hookable"

    def __init__(self, layer):
        self.layer = layer

    def make_hookable(self, model, decoder_path):
        from controlgs_adapter.backend import get_attr_path, set_attr_path

        original = get_attr_path(model, decoder_path)
        set_attr_path(model, decoder_path, nn.Sequential(self.layer))
        return original


def test_defaults_of_wrap():
    model = ScaffoldStandIn(12, seed=2)
    cgs = ControlGS.wrap(model)
    try:
        assert DEFAULT_MODULES == ("lens", "resample", "display") and DEFAULT_ADAPTER == "default"
        assert cgs.modules == DEFAULT_MODULES and cgs.injector.cond_dim == 8 and cgs.adapters == ("default",)
        assert cgs.active_adapter == "default" and cgs.state_blind is False and cgs.placement == "fit"
        assert cgs.backend.name == "scaffold_gs" and cgs.num_anchors == 12 and cgs.rows_per_anchor == 1
        assert [t.decoder for t in cgs.targets] == ["mlp_opacity", "mlp_cov", "mlp_color"]
        assert all((t.in_features, t.out_features, t.from_torchscript) == (35, 32, False) for t in cgs.targets)
        assert cgs.targets[0].as_header() == {"decoder": "mlp_opacity", "fc1": "mlp_opacity.0", "in_features": 35,
                                              "out_features": 32}
        assert {m: (s.lo, s.hi) for m, s in cgs.schedules.items()} == {"lens": (0.0, math.sqrt(2.0)),
                                                                       "resample": (0.0, 3.0), "display": (0.0, 0.8)}
        assert cgs.skipped == [] and cgs.injector.dtype == torch.float32
        assert cgs.fingerprint == ScaffoldGSBackend().fingerprint(model)
    finally:
        cgs.unwrap()


def test_summary_and_repr_text():
    model = script_decoders(ScaffoldStandIn(12, feat_dim=4, n_offsets=2, seed=2))
    cgs = ControlGS.wrap(model, modules=("resample", "display"), cond_dim=3, targets=["mlp_cov"], state_blind=True)
    # conditions 12 * 2 * 3 = 72; projections 2 modules x [4, 3] = 24
    fp = cgs.fingerprint
    assert cgs.summary() == "\n".join([
        "ControlGS on ScaffoldStandIn via backend 'scaffold_gs'",
        f"  anchors: 12 (1 decoder row(s) per anchor), backbone fingerprint {fp}",
        "  modules: resample, display; N = 3 per module; state-blind (strength 1)",
        "  targets:",
        "    mlp_cov.0: Linear(7 -> 4)  (rebuilt from TorchScript)",
        "  schedules:",
        "    resample: ResampleSchedule(log2(d): 0 -> 0, 3 -> 1)",
        "    display: DisplaySchedule(rho: 0 -> 0, 0.8 -> 1)",
        "  trainable: 96 parameters (conditions 72, projections 24)"])
    assert repr(cgs) == ("ControlGS(backend='scaffold_gs', anchors=12, modules=['resample', 'display'], cond_dim=3, "
                         "targets=['mlp_cov.0'], state_blind=True)")
    cgs.unwrap()
    assert repr(cgs).endswith("state_blind=True, unwrapped)")
    assert cgs.summary().splitlines()[0] == "ControlGS on ScaffoldStandIn via backend 'scaffold_gs' (unwrapped)"
    assert isinstance(model.mlp_cov, torch.jit.ScriptModule)  # the original TorchScript decoder is back


def test_module_and_target_refusals_name_the_argument():
    model = ScaffoldStandIn(10, seed=1)
    cases = [
        (dict(modules=("lens", "display", "lens")), InputValueError, "modules lists ['lens'] more than once"),
        (dict(modules=5), InputValueError, "modules must be a sequence of module names, got 5"),
        (dict(cond_dim=True), InputValueError, "cond_dim must be a positive int, got True"),
        (dict(cond_dim=-2), InputValueError, "cond_dim must be a positive int, got -2"),
        (dict(cond_dim=2.0), InputValueError, "cond_dim must be a positive int, got 2.0"),
        (dict(endpoints={"lens": (0.1, 0.5, 0.9)}), InputValueError, "endpoints['lens'] must be (lo, hi), got (0.1, 0.5, 0.9)"),
        (dict(targets="mlp_cov"), TargetError, "targets must be a non-empty sequence of decoder paths, got 'mlp_cov'"),
        (dict(targets=[]), TargetError, "targets must be a non-empty sequence"),
        (dict(name=""), InputValueError, "an adapter name must be a non-empty str, got ''"),
        (dict(name=3), InputValueError, "an adapter name must be a non-empty str, got 3"),
        (dict(backend=5), NoMatchingBackendError, "backend 5 is not registered"),
    ]
    for kw, error, words in cases:
        with pytest.raises(error) as e:
            ControlGS.wrap(model, **kw)
        assert words in str(e.value), kw
        assert ControlGS.attached(model) is None
    # a header's {"lo", "hi"} mapping is taken as the endpoints, and an explicit name
    cgs = ControlGS.wrap(model, modules=("lens",), endpoints={"lens": {"lo": 0.2, "hi": 0.9, "x": 1}}, name="mine")
    assert (cgs.schedules["lens"].lo, cgs.schedules["lens"].hi) == (0.2, 0.9) and cgs.adapters == ("mine",)
    cgs.unwrap()


def test_backend_choice_and_backend_counts_are_checked():
    model = ScaffoldStandIn(10, seed=1)
    assert _describe(ScaffoldGSBackend()) == ("scaffold_gs: Scaffold-GS layout: any object with decoder modules "
                                              "``mlp_opacity``, ``mlp_cov``, ``mlp_color`` and anchors ``get_anchor`` "
                                              "or ``_anchor``")
    nodoc = type("NoDoc", (ScaffoldGSBackend,), {"name": "nodoc", "__doc__": None})
    assert _describe(nodoc()) == "nodoc: NoDoc"
    cgs = ControlGS.wrap(model, backend="scaffold_gs")
    assert cgs.backend.name == "scaffold_gs"
    cgs.unwrap()
    with pytest.raises(NoMatchingBackendError, match=r"backend scaffold_gs: Scaffold-GS layout.* does not recognise a "
                                                     r"SimpleNamespace"):
        ControlGS.wrap(types.SimpleNamespace(mlp_cov=nn.Linear(2, 2)), backend="scaffold_gs")
    with pytest.raises(NoMatchingBackendError, match="picky: Picky test backend.* does not recognise a Linear"):
        ControlGS.wrap(nn.Linear(2, 2), backend=_Picky())
    for backend, error, words in [(_Picky(rows=0), TargetError, "picky: rows_per_anchor must be an int >= 1, got 0"),
                                  (_Picky(rows=2.0), TargetError, "rows_per_anchor must be an int >= 1, got 2.0"),
                                  (_Picky(anchors=0), ShapeError, "picky: the model has 0 anchors and positions [10, 3]"),
                                  (_Picky(anchors=9), ShapeError, "the model has 9 anchors and positions [10, 3]")]:
        with pytest.raises(error) as e:
            ControlGS.wrap(model, backend=backend)
        assert words in str(e.value)
        assert ControlGS.attached(model) is None and not model.mlp_cov[0]._forward_hooks
    cgs = ControlGS.wrap(model, backend=_Picky(rows=2))  # an instance is used as given
    assert cgs.backend.name == "picky" and cgs.rows_per_anchor == 2
    cgs.unwrap()


def test_backbone_tensors_are_frozen_and_restored():
    class Holder:
        pass

    h = Holder()
    h.net = nn.Linear(2, 2)
    h.leaf = torch.zeros(3, requires_grad=True)
    h.derived = h.leaf * 2  # not a leaf: not trainable, not listed
    h.other = 3
    found = _backbone_tensors(h)
    assert {id(t) for t in found} == {id(h.net.weight), id(h.net.bias), id(h.leaf)} and len(found) == 3
    mod = nn.Sequential(nn.Linear(2, 2))
    assert [id(p) for p in _backbone_tensors(mod)] == [id(p) for p in mod.parameters()]
    model = ScaffoldStandIn(10, seed=1)
    model._offset.requires_grad_(False)  # a flag that must come back as it was, not as True
    cgs = ControlGS.wrap(model)
    tensors = [model._anchor, model._anchor_feat, model._offset, *model.mlp_cov.parameters()]
    assert not any(t.requires_grad for t in tensors)
    assert all(p.requires_grad for p in cgs.trainable_parameters())
    cgs.unwrap()
    assert [t.requires_grad for t in tensors[:3]] == [True, True, False] and all(t.requires_grad for t in tensors[3:])
    with pytest.raises(LifecycleError, match="this ControlGS was unwrapped; wrap the model again"):
        cgs.unwrap()
    for call in (lambda: cgs.strengths(RuntimeState()), lambda: cgs.save("x.safetensors"),
                 lambda: cgs.set_adapter("default"), lambda: cgs.conditioned(RuntimeState()).__enter__()):
        with pytest.raises(LifecycleError):
            call()


@pytest.mark.parametrize("dtype, want", [(torch.float64, torch.float64), (torch.float16, torch.float32)])
def test_injector_dtype_follows_fc1_when_float32_or_float64(dtype, want):
    model = ScaffoldStandIn(6, feat_dim=4, n_offsets=2, seed=1, dtype=dtype)
    cgs = ControlGS.wrap(model, modules=("display",))
    assert cgs.injector.dtype == want and cgs.strengths(RuntimeState(power_saving=0.4))["display"].dtype == want
    cgs.unwrap()


def test_anchor_ids_forms_and_refusals():
    model = ScaffoldStandIn(6, feat_dim=4, n_offsets=2, seed=1)
    cgs = ControlGS.wrap(model, modules=("display",))
    assert cgs.anchor_ids(None).tolist() == [0, 1, 2, 3, 4, 5]
    for dt in (torch.int64, torch.int32, torch.int16, torch.uint8, torch.int8):
        got = cgs.anchor_ids(torch.tensor([5, 0, 0], dtype=dt))
        assert got.dtype == torch.int64 and got.tolist() == [5, 0, 0]
    assert cgs.anchor_ids(torch.tensor([], dtype=torch.int64)).tolist() == []
    assert cgs.anchor_ids(torch.tensor([0, 1, 0, 0, 1, 1], dtype=torch.bool)).tolist() == [1, 4, 5]
    for bad, error, words in [([1, 2], InputValueError, "anchor_ids must be a LongTensor[R], a BoolTensor[6] or None, got list"),
                              (torch.tensor([[1]]), ShapeError, "anchor_ids must have shape [R], got [1, 1]"),
                              (torch.tensor([-1, 3]), InputValueError, "anchor_ids must lie in [0, 6), got values in [-1, 3]"),
                              (torch.tensor([6]), InputValueError, "anchor_ids must lie in [0, 6), got values in [6, 6]"),
                              (torch.tensor([1.0]), InputValueError, "integer or bool tensor, got torch.float32")]:
        with pytest.raises(error) as e:
            cgs.anchor_ids(bad)
        assert words in str(e.value)
    cgs.unwrap()


def test_strengths_by_hand_state_blind_and_camera_refusal():
    model = ScaffoldStandIn(6, feat_dim=4, n_offsets=2, seed=1)
    cgs = ControlGS.wrap(model, modules=("resample", "display", "lens"))
    state = RuntimeState(downsample=2.0, power_saving=0.2)
    got = cgs.strengths(state, make_camera(), torch.tensor([3, 1]))
    assert list(got) == ["resample", "display", "lens"]
    # log2(2) / 3 and 0.2 / 0.8, one per requested anchor
    assert got["resample"].tolist() == pytest.approx([1 / 3, 1 / 3], abs=1e-7) and got["display"].tolist() == [0.25, 0.25]
    assert got["lens"].shape == (2,)
    # strengths() lists every module, zeros included (a conditioned block leaves shared zeros out)
    got = cgs.strengths(RuntimeState(), make_camera(), torch.tensor([3, 1, 0]))
    assert got["resample"].tolist() == [0.0] * 3 and got["display"].tolist() == [0.0] * 3
    with pytest.raises(InputValueError, match=r"module 'lens' needs each anchor's screen position: pass "
                                              r"camera=Camera\(...\).*got NoneType"):
        cgs.strengths(state)
    with pytest.raises(InputValueError, match="state must be a RuntimeState, got dict"):
        cgs.strengths({"downsample": 2.0}, make_camera())
    cgs.unwrap()
    blind = ControlGS.wrap(model, modules=("resample", "lens"), state_blind=True)
    got = blind.strengths(RuntimeState(), anchor_ids=torch.tensor([0, 5, 2]))  # no camera needed: strength 1
    assert {m: v.tolist() for m, v in got.items()} == {"resample": [1.0] * 3, "lens": [1.0] * 3}
    assert got["lens"].dtype == torch.float32
    blind.unwrap()


def test_gaze_is_placed_on_the_display_like_the_anchors():
    # "fit" placement on a 64 x 48 image: y is scaled by 48 / 64 = 0.75; an anchor at the gaze has eccentricity 0
    model = ScaffoldStandIn(6, feat_dim=4, n_offsets=2, seed=1)
    cam = make_camera()
    cgs = ControlGS.wrap(model, modules=("foveation",))
    screen = cam.normalized_screen(model._anchor.detach()[[2]])[0]
    gaze = (float(screen[0]), float(screen[1]))
    lam = cgs.strengths(RuntimeState(gaze=gaze), cam, torch.tensor([2]))["foveation"]
    assert float(lam[0]) < 1e-6
    # gaze at the image centre: eccentricity = |(x, 0.75 y)| / sqrt 2
    lam = cgs.strengths(RuntimeState(gaze=(0.0, 0.0)), cam, torch.tensor([2]))["foveation"]
    want = math.hypot(gaze[0], 0.75 * gaze[1]) / math.sqrt(2.0)
    assert math.isclose(float(lam[0]), want, rel_tol=1e-5)
    cgs.placement = "stretch"  # stretched: display positions are the screen positions
    lam = cgs.strengths(RuntimeState(gaze=(0.0, 0.0)), cam, torch.tensor([2]))["foveation"]
    assert math.isclose(float(lam[0]), math.hypot(*gaze) / math.sqrt(2.0), rel_tol=1e-5)
    cgs.unwrap()


def test_conditioned_on_miss_branches_and_zero_row_blocks():
    model = script_decoders(ScaffoldStandIn(6, feat_dim=4, n_offsets=2, seed=1))
    cgs = ControlGS.wrap(model, modules=("display",))
    state = RuntimeState(power_saving=0.4)
    with pytest.warns(RuntimeWarning) as rec:
        with cgs.conditioned(state):
            pass
    msg = str(rec[0].message)
    assert msg.startswith("no wrapped decoder ran inside this conditioned block: the injected first layers "
                          "(mlp_opacity.0, mlp_cov.0, mlp_color.0) of ScaffoldStandIn object at ")
    assert msg.endswith("; the TorchScript decoders ['mlp_opacity', 'mlp_cov', 'mlp_color'] were replaced there by "
                        "eager copies")
    assert rec[0].filename == __file__  # stacklevel: the warning points at the user's with-statement
    with pytest.raises(InjectionMissedError, match="no wrapped decoder ran"):
        with cgs.conditioned(state, on_miss="raise"):
            pass
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        with cgs.conditioned(state, on_miss="ignore"):
            pass
        with cgs.conditioned(state, anchor_ids=torch.zeros(6, dtype=torch.bool), on_miss="raise"):
            pass  # no visible anchor: nothing to render, nothing missed
        x = torch.randn(6, 7)
        with cgs.conditioned(state, on_miss="raise"):
            model.mlp_cov(x)  # one decoder ran: not a miss
    with pytest.raises(InputValueError, match="on_miss must be 'warn', 'raise' or 'ignore', got 'loud'"):
        with cgs.conditioned(state, on_miss="loud"):
            pass
    with pytest.raises(InputValueError, match=r"modules \['lens'\] are not wrapped; wrapped modules: \['display'\]"):
        with cgs.conditioned(state, modules=["lens"]):
            pass
    with pytest.raises(InputValueError, match="modules must be a module name or a sequence of them, got"):
        with cgs.conditioned(state, modules=[1]):
            pass
    # a shared strength of zero is left out of the context; a block with modules=() injects nothing
    with cgs.conditioned(RuntimeState(), on_miss="ignore"):
        assert cgs.injector.context.strengths == {}
    with cgs.conditioned(state, modules=(), on_miss="ignore"):
        assert cgs.injector.context.strengths == {}
    with cgs.conditioned(state, modules="display", on_miss="ignore"):
        assert cgs.injector.context.strengths == {"display": 0.5}
    cgs.unwrap()


def test_adapters_are_named_switched_and_refused(tmp_path):
    model = ScaffoldStandIn(6, feat_dim=4, n_offsets=2, seed=1)
    cgs = ControlGS.wrap(model, modules=("display",))
    with torch.no_grad():
        cgs.injector.conditions.fill_(0.5)
    path = cgs.save(tmp_path / "a.safetensors")
    assert cgs.load_adapter(path, "second") == []
    assert cgs.adapters == ("default", "second") and cgs.active_adapter == "default"
    with pytest.raises(InputValueError, match=r"an adapter named 'second' is already loaded; loaded adapters: "
                                              r"\['default', 'second'\]"):
        cgs.load_adapter(path, "second")
    with pytest.raises(InputValueError, match="an adapter name must be a non-empty str"):
        cgs.load_adapter(path, "")
    with pytest.raises(InputValueError, match=r"unknown adapter 'third'; loaded adapters: \['default', 'second'\]"):
        cgs.set_adapter("third")
    first = cgs.injector
    with cgs.conditioned(RuntimeState(), on_miss="ignore"):
        with pytest.raises(LifecycleError, match="set_adapter inside a conditioned block"):
            cgs.set_adapter("second")
    cgs.set_adapter("default")  # already active: nothing changes
    assert cgs.injector is first and len(first._handles) == 3
    cgs.set_adapter("second")
    assert cgs.injector is not first and cgs.active_adapter == "second" and not first._handles
    assert len(cgs.injector._handles) == 3 and torch.equal(cgs.injector.conditions.detach(), first.conditions.detach())
    x = torch.randn(6, 7)
    ref = model.mlp_cov(x).detach()
    with torch.no_grad():
        cgs.injector.conditions.fill_(1.0)
    with cgs.conditioned(RuntimeState(power_saving=0.4), modules="display"):
        out = model.mlp_cov(x).detach()
    assert not torch.equal(out, ref)  # the second adapter's hooks are live
    cgs.set_adapter("default")
    assert cgs.injector is first
    cgs.unwrap()


def test_torchscript_targets_and_rollback_of_a_failed_hook():
    model = script_decoders(ScaffoldStandIn(6, feat_dim=4, n_offsets=2, seed=1))
    originals = {d: getattr(model, d) for d in ("mlp_opacity", "mlp_cov", "mlp_color")}
    with pytest.raises(TargetError) as e:
        ControlGS.wrap(model, backend=_FC1Elsewhere("mlp_color.0"))
    assert str(e.value) == "fc1_elsewhere: FC1 path 'mlp_color.0' of TorchScript decoder 'mlp_opacity' is not inside it"
    with pytest.raises(TargetError, match="fc1_elsewhere: decoder 'mlp_opacity' has no first layer 'mlp_opacity.7'"):
        ControlGS.wrap(model, backend=_FC1Elsewhere("{}.7"))
    with pytest.raises(TargetError, match=r"fc1_elsewhere: first layer of 'mlp_opacity' must be a Linear, got ReLU"):
        ControlGS.wrap(model, backend=_FC1Elsewhere("{}.1"))
    with pytest.raises(RuntimeError, match="hook failed"):
        ControlGS.wrap(model, backend=_FailingHook())
    # the first decoder had been replaced by its eager copy: put back, nothing attached
    assert all(getattr(model, d) is m for d, m in originals.items())
    assert ControlGS.attached(model) is None
    cgs = ControlGS.wrap(model)
    assert ControlGS.attached(model) is cgs and all(t.from_torchscript for t in cgs.targets)
    assert all(isinstance(getattr(model, d), nn.Sequential) for d in originals)
    cgs.unwrap()
    assert all(getattr(model, d) is m for d, m in originals.items())
    assert ControlGS.attached(nn.Linear(2, 2)) is None  # no backend recognises it


def test_load_adapter_mismatches_with_the_live_wrapper(tmp_path):
    from helpers.adapter_files import rewrite, trained

    from controlgs_adapter.errors import IncompatibleAdapterError

    donor = trained(ScaffoldStandIn(8, feat_dim=4, n_offsets=2, seed=1), seed=3)  # all three targets
    path = donor.save(tmp_path / "all.safetensors")
    want = {k: v.clone() for k, v in donor.injector.state_dict().items()}
    donor.unwrap()
    model = ScaffoldStandIn(8, feat_dim=4, n_offsets=2, seed=1)  # the same backbone
    cgs = ControlGS.wrap(model, targets=["mlp_cov"])
    with pytest.raises(IncompatibleAdapterError) as e:
        cgs.load_adapter(path, "b")
    assert "target 'mlp_opacity': not wrapped (wrapped: ['mlp_cov'])" in str(e.value)
    assert "target 'mlp_color': not wrapped (wrapped: ['mlp_cov'])" in str(e.value) and cgs.adapters == ("default",)
    with pytest.warns(RuntimeWarning, match="non-strict load skipped"):
        skipped = cgs.load_adapter(path, "b", strict=False)
    assert skipped == ["target 'mlp_opacity': not wrapped (wrapped: ['mlp_cov'])",
                       "target 'mlp_color': not wrapped (wrapped: ['mlp_cov'])"]
    cgs.set_adapter("b")
    assert cgs.skipped == skipped and cgs.injector.widths == {"mlp_cov": 4}
    assert all(torch.equal(v, want[k]) for k, v in cgs.injector.state_dict().items())  # what fits loads exactly
    # another rows-per-anchor is only warned about (loaded anyway, not listed as skipped)
    rewrite(path, {"rows_per_anchor": 2})
    with pytest.raises(IncompatibleAdapterError, match="rows per anchor: the adapter expects 2, the model has 1"):
        ControlGS.load(path, ScaffoldStandIn(8, feat_dim=4, n_offsets=2, seed=1))
    other = ScaffoldStandIn(8, feat_dim=4, n_offsets=2, seed=1)
    with pytest.warns(RuntimeWarning, match=r"rows per anchor: the adapter expects 2, the model has 1 \(loaded anyway\)"):
        loaded = ControlGS.load(path, other, strict=False, name="mine")
    assert loaded.adapters == ("mine",) and loaded.active_adapter == "mine" and loaded.skipped == [] and torch.equal(loaded.injector.conditions.detach(), want["conditions"])
    loaded.unwrap()
    # an adapter of another registered backend never loads onto this wrapper, not even non-strict
    rewrite(path, {"backend": "octree_gs", "rows_per_anchor": 1})
    with pytest.raises(IncompatibleAdapterError, match="backend: the adapter was made for 'octree_gs'; this model is "
                                                       "wrapped with scaffold_gs"):
        cgs.load_adapter(path, "c", strict=False)
    assert cgs.adapters == ("default", "b")
    cgs.unwrap()


@pytest.mark.parametrize("layer, shown", [(nn.Linear(7, 5), "Linear(in_features=7, out_features=5, bias=True)"),
                                          (nn.ReLU(), "ReLU()")])
def test_a_backend_whose_make_hookable_breaks_fc1_is_refused_and_rolled_back(layer, shown):
    model = ScaffoldStandIn(6, feat_dim=4, n_offsets=2, seed=1)
    originals = {d: getattr(model, d) for d in ("mlp_opacity", "mlp_cov", "mlp_color")}
    with pytest.raises(TargetError) as e:
        ControlGS.wrap(model, backend=_BadHookable(layer))
    assert str(e.value) == f"bad_hookable: make_hookable left 'mlp_opacity.0' as {shown}"
    assert all(getattr(model, d) is m for d, m in originals.items()) and ControlGS.attached(model) is None
    assert model._anchor.requires_grad  # the backbone was not frozen either


D, P = (1.0, 2.0), (0.0, 0.3, 0.6)


@pytest.fixture(scope="module")
def setup(tiny, tmp_path_factory):
    """The tiny scene's first two training views and an adapter file with random (non-zero) conditions."""
    scene, model = tiny
    views = scene.data.views("train", first=2)
    cgs = ControlGS.wrap(model, cond_dim=4)
    with torch.no_grad(), torch.random.fork_rng(devices=[]):
        torch.manual_seed(3)
        for p in cgs.trainable_parameters():
            p.add_(0.5 * torch.randn_like(p))
    path = cgs.save(tmp_path_factory.mktemp("adapter") / "a.controlgs.safetensors")
    cgs.unwrap()
    return model, views, path


#: the cheap downstream path (no optics) of the every-cell test
CHEAP = {"lens": True, "resample": True, "display": True}


def _pipe(mode: str = "fast", effects: dict | None = None) -> Pipeline:
    pipe = Pipeline.from_config(dict(DEFAULT_EFFECTS if effects is None else effects))
    if "optics" in pipe:
        pipe["optics"].mode = mode
    return pipe.eval()


def _psnr64(eye: torch.Tensor, gt: torch.Tensor) -> float:
    mse = float((eye.clamp(0, 1).double() - gt.double()).square().mean())
    return 10 * math.log10(1.0 / mse)


def test_every_cell_recomputed_by_hand(setup):
    model, views, path = setup
    r = evaluate_grid(model, views, {"mine": path}, downsample=(1, 2), power_saving=P, extra_metrics=False,
                      progress=False, effects=CHEAP)
    assert ControlGS.attached(model) is None  # the adapter is removed afterwards
    assert r.methods == ["no_ss", "ss", IDEAL, "mine"] and r.metrics == ["psnr", "ssim"]
    assert (r.downsample, r.power_saving, r.optics_mode) == (D, P, "fast")
    assert r.info == {"test_views": 2, "test_sizes": ["16x16"]}
    assert all(t.shape == (2, 3, 2) and t.dtype == torch.float64 for mv in r.per_view.values() for t in mv.values())
    pipe, bg = _pipe(effects=CHEAP), views.background
    cgs = ControlGS.load(path, model)
    try:
        with torch.no_grad():
            for v in range(2):
                cam, gt = views[v]
                for i, d in enumerate(D):
                    for j, rho in enumerate(P):
                        state = RuntimeState(downsample=d, power_saving=rho)
                        renders = {"no_ss": render_view(None, model, cam.scaled(d), None, bg),
                                   "ss": render_view(None, model, cam, None, bg), IDEAL: gt,
                                   "mine": render_view(cgs, model, cam, state, bg)}
                        for m, img in renders.items():
                            eye = pipe(img, state, reference=gt)
                            assert float(r.per_view[m]["psnr"][i, j, v]) == pytest.approx(_psnr64(eye, gt), abs=1e-9), (m, d, rho, v)
                            want_ssim = float(ssim(eye.clamp(0, 1).double(), gt.double()))
                            assert float(r.per_view[m]["ssim"][i, j, v]) == pytest.approx(want_ssim, abs=1e-12)
    finally:
        cgs.unwrap()
    # the adapter and the state matter: not the SS-backbone's numbers, not the same in every cell
    assert not torch.allclose(r.per_view["mine"]["psnr"], r.per_view["ss"]["psnr"])
    assert torch.equal(r.per_view["no_ss"]["psnr"][0], r.per_view["ss"]["psnr"][0])  # d = 1: the same render


def test_side_by_side_by_hand(setup):
    model, views, path = setup
    cam, gt = views[0]
    out = side_by_side(model, path, cam, gt, background=views.background)
    assert ControlGS.attached(model) is None
    assert out["settings"] == [(1.0, 0.0), (8.0, 0.8)] and out["gt"] is gt
    assert list(out["rows"]) == ["no_ss", "ss", "controlgs"]
    pipe = _pipe()
    cgs = ControlGS.load(path, model)
    try:
        with torch.no_grad():
            for s, (d, rho) in enumerate(out["settings"]):
                state = RuntimeState(downsample=d, power_saving=rho)
                want = {"no_ss": render_view(None, model, cam.scaled(d), None, views.background),
                        "ss": render_view(None, model, cam, None, views.background),
                        "controlgs": render_view(cgs, model, cam, state, views.background)}
                for m, img in want.items():
                    rendered, eye, p, q = out["rows"][m][s]
                    assert torch.equal(rendered, img), (m, d)
                    ref = pipe(img, state, reference=gt).clamp(0, 1)
                    assert torch.allclose(eye, ref, atol=1e-6) and float(eye.min()) >= 0 and float(eye.max()) <= 1
                    assert p == pytest.approx(_psnr64(ref, gt), abs=1e-6)
                    assert q == pytest.approx(float(ssim(ref.double(), gt.double())), abs=1e-6)
    finally:
        cgs.unwrap()
    assert out["rows"]["no_ss"][1][0].shape == (3, 2, 2)  # rendered at 16 / 8
    one = side_by_side(model, path, cam, gt, settings=[(2, 0.5)], background=views.background)
    assert one["settings"] == [(2.0, 0.5)] and all(len(v) == 1 for v in one["rows"].values())


def test_condition_response_by_hand(setup):
    model, views, path = setup
    cam, _ = views[0]
    bg = views.background
    strips = condition_response(model, path, cam, background=bg)
    assert ControlGS.attached(model) is None
    assert list(strips) == ["resample", "display", "lens"]
    assert [k for k, _ in strips["resample"]] == ["d=1", "d=2", "d=4", "d=8"]
    assert [k for k, _ in strips["display"]] == ["ρ=0%", "ρ=20%", "ρ=40%", "ρ=60%", "ρ=80%"]
    assert [k for k, _ in strips["lens"]] == ["off", "on", "|on - off| x 10"]
    cgs = ControlGS.load(path, model)
    try:
        with torch.no_grad():
            for (_, img), d in zip(strips["resample"], (1.0, 2.0, 4.0, 8.0)):
                assert torch.equal(img, render_view(cgs, model, cam, RuntimeState(downsample=d), bg, modules=("resample",)))
            for (_, img), rho in zip(strips["display"], (0.0, 0.2, 0.4, 0.6, 0.8)):
                assert torch.equal(img, render_view(cgs, model, cam, RuntimeState(power_saving=rho), bg, modules=("display",)))
            off = render_view(None, model, cam, None, bg)
            on = render_view(cgs, model, cam, RuntimeState(), bg, modules=("lens",))
    finally:
        cgs.unwrap()
    assert torch.equal(strips["lens"][0][1], off) and torch.equal(strips["lens"][1][1], on)
    diff = strips["lens"][2][1]
    assert torch.allclose(diff, ((on - off).abs() * 10).clamp(0, 1)) and float(diff.max()) > 0
    # the strips differ along d (the adapter is not zero)
    assert not torch.equal(strips["resample"][0][1], strips["resample"][3][1])
    assert not torch.equal(strips["display"][0][1], strips["display"][4][1])


def test_an_adapter_with_fewer_modules_shows_only_those(setup, tmp_path: Path):
    model, views, _ = setup
    cgs = ControlGS.wrap(model, modules=("display",), cond_dim=2)
    path = cgs.save(tmp_path / "d.controlgs.safetensors")
    cgs.unwrap()
    strips = condition_response(model, path, views[0][0], background=views.background)
    assert list(strips) == ["display"]


pytestmark = pytest.mark.skipif(not (MODEL / "point_cloud").is_dir(), reason="built-in backbone not baked")
