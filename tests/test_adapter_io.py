"""Adapters as safetensors: round trips, fp16 storage, every mismatch named, bad files refused."""

from __future__ import annotations


import pytest
import torch
from safetensors.torch import save_file

from controlgs_adapter import ControlGS, RuntimeState, __version__
from controlgs_adapter.controlgs import ADAPTER_FORMAT_VERSION, ADAPTER_KIND
from controlgs_adapter.errors import FileFormatError, IncompatibleAdapterError
from controlgs_adapter.formats.safetensors import load_tensors, read_header, save_tensors
from controlgs_adapter.formats.adapter import read_spec

from _adapter_files import rewrite, trained
from scaffold_standin import ScaffoldStandIn, make_camera, script_decoders

STATE = RuntimeState(downsample=5.0, power_saving=0.55)


def conditioned_outputs(cgs, model, cam, x):
    with torch.no_grad(), cgs.conditioned(STATE, camera=cam):
        return model.decode(x)


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
