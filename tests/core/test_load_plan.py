"""Loading an adapter file onto a model: every mismatch with the model (backend, anchor count, decoder
widths, backbone fingerprint, tensors, a live wrapper's targets) is listed before anything changes;
a non-strict load skips what does not fit, loads the rest exactly and still refuses what cannot be
skipped; damaged or foreign files are file-format errors."""

from __future__ import annotations

import re
from pathlib import Path
from typing import Any

import pytest
import torch
from helpers.adapter_files import rewrite, saved_adapter, trained
from helpers.scaffold_standin import ScaffoldStandIn
from helpers.wrapping import DECODERS
from safetensors.torch import save_file

from controlgs_adapter import ControlGS
from controlgs_adapter.backends.scaffold_gs import ScaffoldGSBackend
from controlgs_adapter.controlgs import ADAPTER_FORMAT_VERSION, ADAPTER_KIND
from controlgs_adapter.errors import FileFormatError, IncompatibleAdapterError
from controlgs_adapter.formats.adapter import read_spec
from controlgs_adapter.formats.safetensors import load_tensors, save_tensors


@pytest.fixture()
def saved(tmp_path: Path) -> Path:
    """An adapter with random parameters of ``ScaffoldStandIn(30, seed=0)`` (three targets, default modules)."""
    return saved_adapter(tmp_path)


def _problems(path: Path, model: Any, **load: Any) -> list[str]:
    """The mismatches ``ControlGS.load(path, model, **load)`` lists (one per line) when it refuses;
    nothing is left attached to the model."""
    with pytest.raises(IncompatibleAdapterError) as e:
        ControlGS.load(path, model, **load)
    head, *lines = str(e.value).splitlines()
    assert head.startswith(str(path))
    assert _unhooked(model)
    return [line.removeprefix("  - ") for line in lines]


def _matches(patterns: list[str], lines: list[str]) -> bool:
    return len(patterns) == len(lines) and all(re.search(p, line) for p, line in zip(patterns, lines))


def _unhooked(model: Any) -> bool:
    return not any(getattr(model, d)[0]._forward_hooks for d in DECODERS)


def test_another_anchor_count_and_widths_are_each_listed(saved: Path) -> None:
    model = ScaffoldStandIn(31, feat_dim=16)
    file_fp, model_fp = read_spec(saved)["fingerprint"], ScaffoldGSBackend().fingerprint(model)
    assert _matches([r"anchor count.*30.*31",
                     *[rf"target '{d}'.*Linear\(35 -> 32\).*Linear\(19 -> 16\)" for d in DECODERS],
                     rf"backbone fingerprint.*{file_fp}.*{model_fp}", r"targets: none"], _problems(saved, model))


def test_other_backbone_weights_are_a_fingerprint_mismatch_only(saved: Path) -> None:
    other = ScaffoldStandIn(30, seed=1)
    file_fp, model_fp = read_spec(saved)["fingerprint"], ScaffoldGSBackend().fingerprint(other)
    assert file_fp != model_fp
    assert _matches([rf"backbone fingerprint.*{file_fp}.*{model_fp}"], _problems(saved, other))


def test_missing_unexpected_misshapen_and_non_finite_tensors_are_listed_together(saved: Path) -> None:
    rewrite(saved, tensor_changes={"extra.bias": torch.zeros(3), "conditions": torch.zeros(30, 3, 7)},
            drop=("projections.display.d32.weight",))
    assert _matches([r"missing.*\['projections\.display\.d32\.weight'\]", r"unexpected.*\['extra\.bias'\]",
                     r"'conditions'.*\[30, 3, 7\].*\[30, 3, 8\]"], _problems(saved, ScaffoldStandIn(30, seed=0)))
    bad = torch.zeros(30, 3, 8)
    bad[3, 1, 2] = float("nan")
    rewrite(saved, tensor_changes={"conditions": bad})
    assert re.search("'conditions'.*NaN", _problems(saved, ScaffoldStandIn(30, seed=0))[-1])


def test_another_backend_is_refused_even_non_strict(saved: Path) -> None:
    model = ScaffoldStandIn(30, seed=0)
    with pytest.raises(IncompatibleAdapterError, match="none of the adapter's targets"):
        ControlGS.load(saved, ScaffoldStandIn(30, feat_dim=16), strict=False)
    rewrite(saved, {"backend": "octree_gs"})
    for strict in (True, False):
        assert _matches([r"backend.*'octree_gs'.*scaffold_gs"], _problems(saved, model, strict=strict))
    rewrite(saved, {"backend": "no_such_family"})
    assert _matches([r"backend.*'no_such_family'.*not registered.*'scaffold_gs'"], _problems(saved, model))


def test_truncated_foreign_and_other_kind_files_are_file_format_errors(saved: Path, tmp_path: Path) -> None:
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
                        (other_kind, "'psf_bank'"), (newer, f"format_version {ADAPTER_FORMAT_VERSION + 1}.*newer"),
                        (tmp_path / "none.safetensors", "no such file")]:
        with pytest.raises(FileFormatError, match=f"{re.escape(path.name)}.*{words}"):
            ControlGS.load(path, model)
    assert _unhooked(model)


@pytest.mark.parametrize("change, fields", [
    (lambda spec: {"targets": "mlp_opacity", "num_anchors": "30"}, r"\['targets', 'num_anchors'\]"),
    (lambda spec: {"targets": [{"decoder": "mlp_opacity"}]}, r"\['targets\[0\]'\]"),
    (lambda spec: {"schedules": {**spec["schedules"], "lens": {"class": "LensSchedule", "per_anchor": True, "hi": 1.0}}},
     r"\['schedules\.lens'\]"),
    (lambda spec: {"schedules": {**spec["schedules"], "display": {"class": "DisplaySchedule", "per_anchor": False,
                                                                 "lo": 0.0}}}, r"\['schedules\.display'\]"),
], ids=["targets and anchors", "a target's fields", "a schedule without lo", "a schedule without hi"])
def test_malformed_header_fields_are_named(saved: Path, change: Any, fields: str) -> None:
    rewrite(saved, change(read_spec(saved)))
    model = ScaffoldStandIn(30, seed=0)
    with pytest.raises(FileFormatError, match=f"{re.escape(str(saved))}.*{fields}"):
        ControlGS.load(saved, model)
    assert _unhooked(model)


def test_non_strict_skips_extra_and_missing_modules_and_loads_the_rest_exactly(saved: Path) -> None:
    tensors, header = load_tensors(saved, kind=ADAPTER_KIND, max_version=ADAPTER_FORMAT_VERSION)
    extra_target = {"decoder": "mlp_nothing", "fc1": "mlp_nothing.0", "in_features": 35, "out_features": 32}
    rewrite(saved, {"targets": header["targets"] + [extra_target]}, tensor_changes={"extra.bias": torch.zeros(3)},
            drop=("projections.display.d32.weight",))
    with pytest.raises(IncompatibleAdapterError):  # strict stays the default
        ControlGS.load(saved, ScaffoldStandIn(30, seed=0))
    model = ScaffoldStandIn(30, seed=0)
    with pytest.warns(RuntimeWarning, match=f"{re.escape(str(saved))}: non-strict load skipped"):
        cgs = ControlGS.load(saved, model, strict=False)
    assert _matches([r"target 'mlp_nothing'", r"missing.*\['projections\.display\.d32\.weight'\]",
                     r"unexpected.*\['extra\.bias'\]"], cgs.skipped)
    assert [t.decoder for t in cgs.targets] == list(DECODERS)
    state = cgs.injector.state_dict()
    for k, v in tensors.items():
        if k != "projections.display.d32.weight":
            assert torch.equal(state[k], v), k


def test_non_strict_skips_a_misshapen_projection_and_conditions_of_another_anchor_count(saved: Path) -> None:
    tensors = rewrite(saved, tensor_changes={"projections.lens.d32.weight": torch.ones(32, 7)})
    model = ScaffoldStandIn(30, seed=0)
    with pytest.warns(RuntimeWarning, match=re.escape(str(saved))):
        cgs = ControlGS.load(saved, model, strict=False)
    assert _matches([r"'projections\.lens\.d32\.weight'.*\[32, 7\].*\[32, 8\]"], cgs.skipped)
    state = cgs.injector.state_dict()
    assert state["projections.lens.d32.weight"].shape == (32, 8)
    assert all(torch.equal(state[k], v) for k, v in tensors.items() if k != "projections.lens.d32.weight")
    cgs.unwrap()

    other = ScaffoldStandIn(31, seed=0)  # other anchors: conditions skipped (stay zero), projections load
    with pytest.warns(RuntimeWarning, match=r"backbone fingerprint.*\(loaded anyway\)"):
        cgs = ControlGS.load(saved, other, strict=False)
    assert _matches([r"anchor count.*30.*31", r"'projections\.lens\.d32\.weight'.*\[32, 7\].*\[32, 8\]"], cgs.skipped)
    assert torch.equal(cgs.injector.conditions.detach(), torch.zeros(31, 3, 8))
    assert torch.equal(cgs.injector.state_dict()["projections.display.d32.weight"], tensors["projections.display.d32.weight"])


def test_load_adapter_checks_the_file_against_the_live_wrapper(tmp_path: Path) -> None:
    """Another adapter of the same backbone loads onto a live wrapper only where its targets are wrapped;
    another rows-per-anchor is refused strictly and only warned about non-strictly; another backend
    never loads."""
    donor = trained(ScaffoldStandIn(8, feat_dim=4, n_offsets=2, seed=1), seed=3)  # all three targets
    path = donor.save(tmp_path / "all.safetensors")
    want = {k: v.clone() for k, v in donor.injector.state_dict().items()}
    donor.unwrap()
    model = ScaffoldStandIn(8, feat_dim=4, n_offsets=2, seed=1)  # the same backbone
    cgs = ControlGS.wrap(model, targets=["mlp_cov"])
    not_wrapped = [rf"target '{d}'.*not wrapped.*\['mlp_cov'\]" for d in ("mlp_opacity", "mlp_color")]
    with pytest.raises(IncompatibleAdapterError) as e:
        cgs.load_adapter(path, "b")
    assert _matches(not_wrapped, str(e.value).splitlines()[1:]) and cgs.adapters == ("default",)
    with pytest.warns(RuntimeWarning, match=re.escape(str(path))):
        skipped = cgs.load_adapter(path, "b", strict=False)
    assert _matches(not_wrapped, skipped)
    cgs.set_adapter("b")
    assert cgs.skipped == skipped and cgs.injector.widths == {"mlp_cov": 4}
    assert all(torch.equal(v, want[k]) for k, v in cgs.injector.state_dict().items())  # what fits loads exactly

    rewrite(path, {"rows_per_anchor": 2})
    assert _matches([r"rows per anchor.*2.*1"], _problems(path, ScaffoldStandIn(8, feat_dim=4, n_offsets=2, seed=1)))
    other = ScaffoldStandIn(8, feat_dim=4, n_offsets=2, seed=1)
    with pytest.warns(RuntimeWarning, match=r"rows per anchor.*2.*1 \(loaded anyway\)"):
        loaded = ControlGS.load(path, other, strict=False, name="mine")
    assert loaded.adapters == ("mine",) and loaded.active_adapter == "mine" and loaded.skipped == []
    assert torch.equal(loaded.injector.conditions.detach(), want["conditions"])
    loaded.unwrap()

    rewrite(path, {"backend": "octree_gs", "rows_per_anchor": 1})
    with pytest.raises(IncompatibleAdapterError, match=r"backend.*'octree_gs'.*wrapped with scaffold_gs"):
        cgs.load_adapter(path, "c", strict=False)
    assert cgs.adapters == ("default", "b")
    cgs.unwrap()
