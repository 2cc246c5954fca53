"""The adapter file (``formats.adapter``): its header fields and schedule endpoints checked on reading, the
tensors checked against the header, the backbone fingerprint, conditions mapped onto another anchor order,
and the dtypes it is written in."""

from __future__ import annotations

import math
import re

import pytest
import torch
from helpers.adapter_files import rewrite, trained
from helpers.contextgs_files import PAD, A, _arrays, _decoders, _model, _write_dir
from helpers.rawfiles import write_raw
from helpers.scaffold_standin import ScaffoldStandIn

from controlgs_adapter import ControlGS
from controlgs_adapter.backends.contextgs import ContextGSBackend, load_contextgs_dir
from controlgs_adapter.controlgs import ADAPTER_KIND
from controlgs_adapter.errors import FileFormatError, InputValueError, NonFiniteError
from controlgs_adapter.formats.adapter import (
    check_header,
    fingerprint_mismatch,
    map_conditions,
    read_spec,
    read_tensors,
    row_map,
    tensor_mismatches,
    valid_fingerprint,
    write_adapter,
)
from controlgs_adapter.formats.safetensors import load_tensors

pytestmark = pytest.mark.filterwarnings("ignore::DeprecationWarning")


@pytest.fixture
def saved(tmp_path):
    model = ScaffoldStandIn(6, feat_dim=4, n_offsets=2, seed=1)
    cgs = trained(model, modules=("lens", "display"))
    path = tmp_path / "scene.controlgs.safetensors"
    cgs.save(path)
    header = read_spec(path)
    cgs.unwrap()
    return model, path, header["schedules"]


@pytest.mark.parametrize("lo, hi", [(math.nan, 1.0), (0.0, math.inf), (-math.inf, 0.5), (0.25, 0.25)])
def test_schedule_endpoints_that_make_no_schedule_are_refused_naming_the_file(saved, lo, hi):
    model, path, schedules = saved
    rewrite(path, {"schedules": {**schedules, "display": {**schedules["display"], "lo": lo, "hi": hi}}})
    with pytest.raises(FileFormatError, match=rf"{path.name}: adapter header field schedules\.display: endpoints "
                                              rf"lo={lo!r}, hi={hi!r}"):
        ControlGS.load(path, model)
    assert ControlGS.attached(model) is None  # nothing was wrapped


def test_valid_schedule_endpoints_load(saved):
    model, path, schedules = saved
    rewrite(path, {"schedules": {**schedules, "display": {**schedules["display"], "lo": 0.1, "hi": 0.7}}})
    cgs = ControlGS.load(path, model)
    assert (cgs.schedules["display"].lo, cgs.schedules["display"].hi) == (0.1, 0.7)
    cgs.unwrap()


def _spec(**over):
    base = {"backend": "b", "modules": ["lens", "display"], "cond_dim": 2, "schedules": {
        "lens": {"lo": 0, "hi": 1.5}, "display": {"lo": 0.0, "hi": 1}}, "state_blind": False,
        "targets": [{"decoder": "mlp_color", "in_features": 3, "out_features": 4},
                    {"decoder": "mlp_opacity", "in_features": 3, "out_features": 6},
                    {"decoder": "mlp_cov", "in_features": 3, "out_features": 4}],
        "num_anchors": 5, "rows_per_anchor": 1, "fingerprint": "f"}
    return {**base, **over}


@pytest.mark.parametrize("over, bad", [
    (dict(backend=1), ["backend"]), (dict(modules="lens"), ["modules"]), (dict(cond_dim=2.0), ["cond_dim"]),
    (dict(state_blind=None), ["state_blind"]), (dict(num_anchors="5"), ["num_anchors"]),
    (dict(rows_per_anchor=None), ["rows_per_anchor"]), (dict(fingerprint=3), ["fingerprint"]),
    (dict(schedules={"lens": {"lo": 0, "hi": 1}}), ["schedules.display"]),
    (dict(schedules={"lens": {"lo": 0, "hi": "1"}, "display": {"lo": 0, "hi": 1}}), ["schedules.lens"]),
    (dict(schedules={"lens": {"lo": 0, "hi": 1}, "display": [0, 1]}), ["schedules.display"]),
    (dict(targets=[{"decoder": "d", "in_features": 3, "out_features": 4}, {"decoder": "d", "in_features": 3}]),
     ["targets[1]"]),
    (dict(targets=[{"decoder": 1, "in_features": 3, "out_features": 4}]), ["targets[0]"]),
    (dict(targets=["d"]), ["targets[0]"]),
])
def test_malformed_header_fields_are_named(over, bad):
    assert check_header("a.safetensors", _spec()) == _spec()
    with pytest.raises(FileFormatError, match=rf"^a\.safetensors: .*{re.escape(str(bad))}$"):
        check_header("a.safetensors", _spec(**over))


def test_tensor_mismatches_by_hand():
    spec = _spec()
    good = {"conditions": torch.zeros(5, 2, 2), **{f"projections.{m}.d{d}.weight": torch.zeros(d, 2)
                                                   for m in ("lens", "display") for d in (4, 6)}}
    assert tensor_mismatches(good, spec) == []
    bad = {**good, "conditions": torch.zeros(5, 2, 3), "projections.lens.d4.weight": torch.zeros(4, 2, dtype=torch.int32),
           "projections.display.d6.weight": torch.full((6, 2), math.inf), "junk": torch.zeros(1)}
    del bad["projections.lens.d6.weight"]
    got = tensor_mismatches(bad, spec)
    assert got == [
        ("tensors missing from the file: ['projections.lens.d6.weight']", frozenset({"projections.lens.d6.weight"})),
        ("unexpected tensors in the file: ['junk']", frozenset({"junk"})),
        ("tensor 'conditions': shape [5, 2, 3], expected [5, 2, 2]", frozenset({"conditions"})),
        ("tensor 'projections.display.d6.weight': contains NaN/Inf", frozenset({"projections.display.d6.weight"})),
        ("tensor 'projections.lens.d4.weight': dtype torch.int32, expected a floating-point type",
         frozenset({"projections.lens.d4.weight"})),
    ]


def test_fingerprint_mismatch_and_condition_mapping_by_hand():
    assert fingerprint_mismatch({"fingerprint": "abc"}, "abc") == []
    (msg, skip), = fingerprint_mismatch({"fingerprint": "abc"}, "xyz")
    assert "trained on backbone abc, this model is xyz" in msg and skip is None
    saved = torch.arange(6.0).view(3, 1, 2)
    gathered = map_conditions(saved, ("gather", torch.tensor([2, 0])), 2)
    assert gathered.tolist() == [[[4.0, 5.0]], [[0.0, 1.0]]]
    scattered = map_conditions(saved, ("scatter", torch.tensor([4, 1, 0])), 5)
    assert scattered.tolist() == [[[4.0, 5.0]], [[2.0, 3.0]], [[0.0, 0.0]], [[0.0, 0.0]], [[0.0, 1.0]]]


def test_write_adapter_dtype_choices(tmp_path):
    t = {"conditions": torch.tensor([[[1.0, -70000.0]]]), "projections.lens.d4.weight": torch.ones(4, 2)}
    spec = _spec(modules=["lens"], num_anchors=1, schedules={"lens": {"lo": 0, "hi": 1}})
    with pytest.raises(InputValueError, match="dtype must be None, torch.float16 or torch.float32, got torch.float64"):
        write_adapter(tmp_path / "a.safetensors", t, spec, dtype=torch.float64)
    with pytest.raises(NonFiniteError, match=r"a.safetensors: conditions reach \|7e\+04\|, beyond float16's range \(65504\)"):
        write_adapter(tmp_path / "a.safetensors", t, spec, dtype=torch.float16)
    assert not (tmp_path / "a.safetensors").exists()
    t["conditions"] = torch.tensor([[[1.0, -65504.0]]])
    write_adapter(tmp_path / "a.safetensors", t, spec, dtype=torch.float16)
    assert read_spec(tmp_path / "a.safetensors")["condition_dtype"] == "float16"
    assert read_tensors(tmp_path / "a.safetensors")["conditions"].dtype == torch.float16
    write_adapter(tmp_path / "b.safetensors", {**t, "conditions": t["conditions"].double()}, spec)
    assert read_spec(tmp_path / "b.safetensors")["condition_dtype"] == "float64"
    write_adapter(tmp_path / "c.safetensors", {**t, "conditions": t["conditions"].double()}, spec, dtype=torch.float32)
    assert read_tensors(tmp_path / "c.safetensors")["conditions"].dtype == torch.float32
    write_adapter(tmp_path / "d.safetensors", {**t, "conditions": torch.zeros(0, 1, 2)}, {**spec, "num_anchors": 0},
                  dtype=torch.float16)


def test_row_map_bounds_the_source_index_by_the_saved_rows(tmp_path):
    """A loaded model that dropped anchors of the saved one (invalid, padding) maps the saved condition rows
    by its source index, only while every index is a saved row."""
    arr, decs = _arrays(7, decoded=True), _decoders(7)
    arr["mask"][3] = 0.0
    live, loaded = _model(arr, decs, decoded=True), load_contextgs_dir(_write_dir(tmp_path / "s", arr, decs))
    backend = ContextGSBackend()
    spec = {"valid_fingerprint": valid_fingerprint(live, backend), "num_anchors": A}
    kind, rows = row_map(loaded, backend, spec)
    assert kind == "gather" and rows.tolist() == [i for i in range(A - PAD) if i != 3]
    source = loaded.source_index.clone()
    loaded.source_index = source.clone()
    loaded.source_index[-1] = A - 1  # the last saved row: still a row of the file
    assert row_map(loaded, backend, spec)[0] == "gather"
    loaded.source_index[-1] = A  # one past the saved rows: no mapping
    assert row_map(loaded, backend, spec) is None
    assert row_map(loaded, backend, {**spec, "valid_fingerprint": 1}) is None
    loaded.source_index = source
    assert row_map(loaded, backend, {**spec, "num_anchors": A - PAD - 1}) is None  # same count: nothing to map


# ------------------------------------------------------------------------------ adapter file headers
HEADER_CASES = [
    ("format_version true", {"format_version": True}, "format_version.*True"),
    ("format_version '1'", {"format_version": "1"}, "format_version.*'1'"),
    ("format_version 0", {"format_version": 0}, "format_version.*0"),
    ("format_version 1.0", {"format_version": 1.0}, r"format_version.*1\.0"),
    ("format_version 99", {"format_version": 99}, "format_version 99"),
    ("header a list", {"raw_header": "[1, 2]"}, "JSON object"),
    ("header not JSON", {"raw_header": "{oops"}, "corrupt"),
    ("header deep JSON", {"raw_header": "[" * 100000 + "]" * 100000}, "corrupt"),
    ("other kind", {"kind": "psf_bank"}, "'psf_bank'"),
]


@pytest.mark.parametrize("kw, pattern", [c[1:] for c in HEADER_CASES], ids=[c[0] for c in HEADER_CASES])
def test_bad_adapter_file_headers_are_file_format_errors(tmp_path, kw, pattern):
    p = write_raw(tmp_path / "f.safetensors", {"w": torch.zeros(2)}, {}, **{"kind": ADAPTER_KIND, **kw})
    with pytest.raises(FileFormatError, match=f"f.safetensors.*{pattern}"):
        load_tensors(p, kind=ADAPTER_KIND, max_version=1)


# ------------------------------------------------------------------------------ the foveation module's visual angles
def _angles_header() -> dict:
    """A valid 3 x 4 visual-angle map: tangents (x / 2, y / 3) at linspace(-1, 1, 4) x linspace(-1, 1, 3)."""
    return {"tangents": [[[x / 2, y / 3] for x in (-1.0, -1 / 3, 1 / 3, 1.0)] for y in (-1.0, 0.0, 1.0)],
            "display_mm": [24.0, 18.0], "axis": [0.0, 0.0]}


def _angles_with(field: str, value) -> dict:
    return {**_angles_header(), field: value}


_NAN_TANGENTS = _angles_header()["tangents"]
_NAN_TANGENTS[1][2][0] = math.nan


@pytest.mark.parametrize("angles, field", [
    (_angles_with("tangents", _NAN_TANGENTS), r"visual_angles\.tangents: holds NaN"),
    (_angles_with("tangents", [[[0.0, 0.0, 0.0]] * 2] * 2), r"visual_angles\.tangents: must be \[Sy, Sx, 2\].*\[2, 2, 3\]"),
    (_angles_with("tangents", [[[0.0, 0.0]] * 2]), r"visual_angles\.tangents: must be \[Sy, Sx, 2\].*\[1, 2, 2\]"),
    (_angles_with("tangents", [[[0.0, 0.0]] * 66] * 2), r"visual_angles\.tangents: must be \[Sy, Sx, 2\].*\[2, 66, 2\]"),
    (_angles_with("tangents", [[[0.0, 0.0]], [[0.0, 0.0], [1.0, 1.0]]]), r"visual_angles\.tangents: must be Sy x Sx x 2"),
    (_angles_with("tangents", [[[True, 0.0]] * 2] * 2), r"visual_angles\.tangents: must be Sy x Sx x 2 nested lists"),
    (_angles_with("tangents", None), r"visual_angles\.tangents: must be Sy x Sx x 2"),
    (_angles_with("display_mm", [24.0, 0.0]), r"visual_angles\.display_mm: must be two finite numbers > 0"),
    (_angles_with("display_mm", [24.0, math.nan]), r"visual_angles\.display_mm: must be two finite numbers > 0"),
    (_angles_with("axis", [0.0, math.inf]), r"visual_angles\.axis: must be two finite numbers"),
    (_angles_with("axis", "centre"), r"visual_angles\.axis: must be two finite numbers"),
    (_angles_with("extra", 1), r"visual_angles: unknown field\(s\) \['extra'\]"),
    ([1.0], r"visual_angles: must be an object, got list"),
])
def test_hostile_visual_angles_are_refused_naming_the_file_and_field(tmp_path, angles, field):
    cgs = trained(ScaffoldStandIn(30), modules=("display", "foveation"))
    path = cgs.save(tmp_path / "a.safetensors")
    tensors, header = load_tensors(path, kind=ADAPTER_KIND, max_version=3)
    header = {k: v for k, v in header.items() if k not in ("kind", "format_version", "library_version")}
    write_raw(path, tensors, {**header, "visual_angles": angles}, kind=ADAPTER_KIND, format_version=3)
    with pytest.raises(FileFormatError, match=rf"a\.safetensors: adapter header field {field}"):
        ControlGS.load(path, cgs.unwrap())
    assert ControlGS.attached(cgs.model) is None  # nothing was wrapped


def test_visual_angles_need_the_foveation_module(tmp_path):
    cgs = trained(ScaffoldStandIn(30), modules=("display",))
    path = cgs.save(tmp_path / "a.safetensors")
    rewrite(path, {"visual_angles": _angles_header()})
    with pytest.raises(FileFormatError, match=r"a\.safetensors: adapter header field visual_angles: only the "
                                              r"'foveation' module has one"):
        read_spec(path)


def test_a_recorded_map_is_read_on_its_grid(tmp_path):
    cgs = trained(ScaffoldStandIn(30), modules=("display", "foveation"))
    path = cgs.save(tmp_path / "a.safetensors")
    rewrite(path, {"visual_angles": _angles_header()})
    angles = ControlGS.load(path, cgs.unwrap()).schedules["foveation"].lens_angles
    xy = torch.tensor([[0.25, -0.5], [-1.0, 1.0], [0.7, 0.1]], dtype=torch.float64)
    want = torch.rad2deg(torch.atan(xy / torch.tensor([2.0, 3.0], dtype=torch.float64)))  # the map is linear
    torch.testing.assert_close(angles.directions(xy), want, rtol=0, atol=1e-12)
    assert (angles.display_mm, angles.axis, list(angles.tangents.shape)) == ((24.0, 18.0), (0.0, 0.0), [3, 4, 2])
