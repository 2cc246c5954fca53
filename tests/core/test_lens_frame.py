"""The lens frame: radius for a centred symmetric lens (today's strengths bit for bit), q = G(p) - G(axis)
through the green chief-ray map for any other lens (against an affine map, where bilinear interpolation is
exact), the override, the frame recorded in the adapter file and hostile headers."""

from __future__ import annotations

import math

import pytest
import torch
from helpers.adapter_files import trained
from helpers.banks import affine_bank
from helpers.rawfiles import write_raw
from helpers.scaffold_standin import ScaffoldStandIn, make_camera
from helpers.wrapping import assert_same_outputs, conditioned_decode
from hypothesis import given, settings
from hypothesis import strategies as st

from controlgs_adapter import ControlGS, RuntimeState
from controlgs_adapter.controlgs import ADAPTER_KIND
from controlgs_adapter.downstream.optics.bank import PSFBank
from controlgs_adapter.downstream.placement import to_display
from controlgs_adapter.errors import FileFormatError, InputValueError
from controlgs_adapter.formats.safetensors import load_tensors, read_header
from controlgs_adapter.lens_frame import LensFrame

D64 = torch.float64
A = [[0.75, 0.125], [-0.25, 1.5]]  # exact in float32, as the bank stores its chief rays
B = [0.0625, -0.125]
AXIS = (0.25, -0.125)


def _hand_q(p: torch.Tensor, axis=AXIS) -> torch.Tensor:
    """q = G(p) - G(axis) = A (clamp(p) - axis) for the affine G, in float64."""
    return (p.double().clamp(-1, 1) - torch.tensor(axis, dtype=D64)) @ torch.tensor(A, dtype=D64).T


def _display_positions(model: ScaffoldStandIn, cam, placement="fit") -> torch.Tensor:
    screen = cam.normalized_screen(model.get_anchor.detach())
    return to_display(screen, cam.height, cam.width, placement)


def test_the_shipped_cardboard_bank_gives_exactly_todays_strengths():
    """Cardboard is rotationally symmetric and centred: a radius frame about (0, 0), and every lens strength
    bit for bit ||p|| / sqrt 2 (clamped) as without a lens, for a square and a 16:9 camera."""
    bank = PSFBank.default()
    frame = LensFrame.from_bank(bank)
    assert (frame.mode, frame.axis, frame.field_map, frame.is_default) == ("radius", (0.0, 0.0), None, True)
    model = ScaffoldStandIn(seed=3)
    with_lens = ControlGS.wrap(model, modules=("lens", "display"), lens=bank)
    assert with_lens.lens_frame == LensFrame()
    for cam in (make_camera(width=36, height=36), make_camera(width=64, height=36)):
        got = with_lens.strengths(RuntimeState(power_saving=0.2), cam)["lens"]
        p = _display_positions(model, cam)
        assert torch.equal(got, (torch.linalg.vector_norm(p, dim=-1) / math.sqrt(2)).clamp(0, 1).float())
    with_lens.unwrap()
    plain = ControlGS.wrap(model, modules=("lens", "display"))
    cam = make_camera(width=64, height=36)
    want = plain.strengths(RuntimeState(), cam)["lens"]
    plain.unwrap()
    again = ControlGS.wrap(model, modules=("lens", "display"), lens=bank)
    assert torch.equal(again.strengths(RuntimeState(), cam)["lens"], want)
    again.unwrap()


def test_a_decentred_lens_gives_q_in_the_lens_frame_from_the_green_chief_rays():
    bank = affine_bank(A, B, axis=AXIS)
    assert not bank.rotationally_symmetric
    frame = LensFrame.from_bank(bank)
    assert frame.mode == "xy" and frame.axis == AXIS and frame.field_map.shape == (17, 17, 2)
    g = torch.Generator().manual_seed(0)
    p = torch.cat([torch.rand(200, 2, generator=g, dtype=D64) * 2 - 1,
                   torch.tensor([[0.0, 0.0], list(AXIS), [1.0, -1.0], [2.5, 0.3], [-7.0, 9.0]], dtype=D64)])
    q = frame.lens_coords(p)
    assert torch.allclose(q, _hand_q(p), atol=1e-12, rtol=0)
    assert torch.equal(frame.lens_coords(torch.tensor([list(AXIS)], dtype=D64)), torch.zeros(1, 2, dtype=D64))
    assert torch.allclose(frame.lens_coords(p.float()), _hand_q(p).float(), atol=1e-6)
    behind = frame.lens_coords(torch.full((1, 2), math.inf, dtype=D64))  # behind the camera: a corner, finite
    assert torch.allclose(behind, _hand_q(torch.ones(1, 2, dtype=D64)), atol=1e-12)
    # a symmetric lens set off the centre is not centred: also (x, y)
    assert LensFrame.from_bank(affine_bank(A, B, axis=AXIS, symmetric=True)).mode == "xy"
    assert LensFrame.from_bank(affine_bank(A, B, symmetric=True)).mode == "radius"


@settings(max_examples=30, deadline=None)
@given(st.lists(st.tuples(st.floats(-1.5, 1.5), st.floats(-1.5, 1.5)), min_size=1, max_size=20),
       st.tuples(st.floats(-0.5, 0.5), st.floats(-0.5, 0.5)))
def test_q_is_the_affine_map_of_the_offset_from_the_axis_anywhere(points, axis):
    frame = LensFrame.from_bank(affine_bank(A, B, axis=axis))
    p = torch.tensor(points, dtype=D64)
    assert torch.allclose(frame.lens_coords(p), _hand_q(p, axis), atol=1e-12, rtol=0)


def test_strengths_in_the_xy_frame_by_hand():
    """lambda = clamp(q / hi, -1, 1) per axis, signed, with q from each anchor's display position."""
    model, cam = ScaffoldStandIn(seed=1), make_camera(width=64, height=36)
    cgs = ControlGS.wrap(model, modules=("display", "lens"), cond_dim=4, lens=affine_bank(A, B, axis=AXIS),
                         endpoints={"lens": (0.1, 0.6)})
    lam = cgs.strengths(RuntimeState(power_saving=0.4), cam)
    assert lam["lens"].shape == (40, 2) and lam["display"].shape == (40,)
    want = (_hand_q(_display_positions(model, cam)) / 0.6).clamp(-1, 1)
    assert torch.allclose(lam["lens"].double(), want, atol=1e-6)
    assert float(want.min()) < 0 < float(want.max()) and 0 < float(want.abs().min()) and float(want.abs().max()) == 1
    assert torch.equal(cgs.strengths(RuntimeState(), cam, torch.tensor([5, 2]))["lens"], lam["lens"][[5, 2]])
    cgs.unwrap()


def test_the_override_compares_radius_and_xy_on_one_lens():
    """lens_conditioning="radius" on a decentred lens: ||p - axis||; "xy" on the symmetric Cardboard lens:
    finite, signed like p, zero at the centre, and growing with the radius along an axis."""
    model, cam = ScaffoldStandIn(seed=2), make_camera(width=48, height=48)
    p = _display_positions(model, cam).double()
    radius = ControlGS.wrap(model, modules=("lens",), lens=affine_bank(A, B, axis=AXIS), lens_conditioning="radius")
    assert radius.lens_frame == LensFrame("radius", AXIS)
    want = ((p - torch.tensor(AXIS, dtype=D64)).norm(dim=1) / math.sqrt(2)).clamp(0, 1)
    assert torch.allclose(radius.strengths(RuntimeState(), cam)["lens"].double(), want, atol=1e-6)
    radius.unwrap()

    xy = ControlGS.wrap(model, modules=("lens",), lens=PSFBank.default(), lens_conditioning="xy")
    lam = xy.strengths(RuntimeState(), cam)["lens"]
    assert lam.shape == (40, 2) and bool(torch.isfinite(lam).all()) and float(lam.abs().max()) <= 1
    assert torch.equal(torch.sign(lam), torch.sign(p).float())
    frame = xy.lens_frame
    assert torch.equal(frame.lens_coords(torch.zeros(1, 2, dtype=D64)), torch.zeros(1, 2, dtype=D64))
    along = frame.lens_coords(torch.tensor([[r, 0.0] for r in (0.2, 0.4, 0.6, 0.8, 1.0)], dtype=D64))
    assert bool((along[1:, 0] > along[:-1, 0]).all()) and float(along[:, 1].abs().max()) < 1e-6
    xy.unwrap()


@pytest.mark.parametrize("kw, match", [
    ({"lens_conditioning": "xy", "cond_dim": 7}, r"cond_dim must be even.*got 7"),
    ({"lens_conditioning": "polar"}, r"lens_conditioning.*'polar'"),
    ({"lens": "cardboard.safetensors"}, r"lens must be a PSFBank or a LensFrame, got str"),
    ({"lens": None, "lens_conditioning": "xy"}, r"lens_conditioning='xy' needs the lens's field map.*got None"),
    ({"modules": ("display",), "lens_conditioning": "xy"}, r"'xy' needs the 'lens' module.*\['display'\]"),
])
def test_wrap_refuses_a_lens_condition_it_cannot_build(kw, match):
    kw = {"lens": affine_bank(A, B, axis=AXIS), "modules": ("lens", "display"), **kw}
    model = ScaffoldStandIn()
    with pytest.raises(InputValueError, match=match):
        ControlGS.wrap(model, **kw)
    assert ControlGS.attached(model) is None


def test_a_decentred_lens_without_a_lens_module_records_no_frame(tmp_path):
    cgs = ControlGS.wrap(ScaffoldStandIn(), modules=("display",), lens=affine_bank(A, B, axis=AXIS))
    assert cgs.lens_frame == LensFrame() and "lens_frame" not in cgs.header()
    cgs.unwrap()


@pytest.mark.parametrize("conditioning", ["xy", "radius"])
def test_save_load_keeps_the_frame_and_the_outputs(tmp_path, conditioning):
    model, cam = ScaffoldStandIn(seed=4), make_camera(width=64, height=36)
    x = torch.randn(40, 35, generator=torch.Generator().manual_seed(1))
    state = RuntimeState(power_saving=0.3)
    cgs = trained(model, modules=("lens", "display"), cond_dim=4, lens=affine_bank(A, B, axis=AXIS),
                  lens_conditioning=conditioning)
    want, lam = conditioned_decode(cgs, model, x, state, camera=cam), cgs.strengths(state, cam)["lens"]
    path = cgs.save(tmp_path / "a.safetensors")
    cgs.unwrap()
    h = read_header(path, kind=ADAPTER_KIND, max_version=2)
    assert h["format_version"] == 2 and h["lens_frame"]["mode"] == conditioning and h["lens_frame"]["axis"] == list(AXIS)
    loaded = ControlGS.load(path, model)
    assert loaded.lens_frame == cgs.lens_frame
    assert torch.equal(loaded.strengths(state, cam)["lens"], lam)
    assert_same_outputs(want, conditioned_decode(loaded, model, x, state, camera=cam))
    assert ("lens condition: LensFrame" in loaded.summary()) is True
    # a second adapter keeps its own frame; switching follows it
    plain = trained(ScaffoldStandIn(seed=4), modules=("lens", "display"), cond_dim=4)
    other = plain.save(tmp_path / "b.safetensors")
    plain.unwrap()
    loaded.load_adapter(other, "plain")
    loaded.set_adapter("plain")
    assert loaded.lens_frame == LensFrame() and loaded.strengths(state, cam)["lens"].shape == (40,)
    loaded.set_adapter("default")
    assert loaded.lens_frame == cgs.lens_frame
    loaded.unwrap()


def test_a_file_without_a_frame_loads_as_a_centred_radius_frame(tmp_path):
    """Format-1 files have no lens_frame: radius about (0, 0)."""
    model, cam = ScaffoldStandIn(seed=5), make_camera()
    cgs = trained(model, modules=("lens", "display"), cond_dim=4, lens=affine_bank(A, B, axis=AXIS))
    path = cgs.save(tmp_path / "a.safetensors")
    cgs.unwrap()
    tensors, header = load_tensors(path, kind=ADAPTER_KIND, max_version=2)
    header = {k: v for k, v in header.items() if k not in ("kind", "format_version", "library_version", "lens_frame")}
    write_raw(path, tensors, header, kind=ADAPTER_KIND, format_version=1)
    loaded = ControlGS.load(path, model)
    assert loaded.lens_frame == LensFrame()
    want = (torch.linalg.vector_norm(_display_positions(model, cam), dim=-1) / math.sqrt(2)).clamp(0, 1)
    assert torch.equal(loaded.strengths(RuntimeState(), cam)["lens"], want)
    loaded.unwrap()


def _xy_header() -> dict:
    return LensFrame.from_bank(affine_bank(A, B, axis=AXIS)).header()


def _with(field: str, value) -> dict:
    h = _xy_header()
    h[field] = value
    return h


_NAN_MAP = _xy_header()["field_map"]
_NAN_MAP[3][4][1] = math.nan


@pytest.mark.parametrize("frame, field", [
    (_with("field_map", _NAN_MAP), r"lens_frame\.field_map: holds NaN"),
    (_with("field_map", _xy_header()["field_map"][:16]), r"lens_frame\.field_map: must be \[S, S, 2\].*\[16, 17, 2\]"),
    (_with("field_map", [[[0.0, 0.0, 0.0]] * 2] * 2), r"lens_frame\.field_map: must be \[S, S, 2\].*\[2, 2, 3\]"),
    (_with("field_map", [[[0.0, 0.0]], [[0.0, 0.0], [1.0, 1.0]]]), r"lens_frame\.field_map: must be S x S x 2"),
    (_with("field_map", [[["0", 0.0]] * 2] * 2), r"lens_frame\.field_map: must be S x S x 2 nested lists of numbers"),
    (_with("field_map", None), r"lens_frame\.field_map: must be S x S x 2"),
    (_with("mode", "polar"), r"lens_frame\.mode: must be one of \('radius', 'xy'\), got 'polar'"),
    (_with("axis", [0.0, math.inf]), r"lens_frame\.axis: must be two finite numbers"),
    (_with("axis", [0.0]), r"lens_frame\.axis: must be two finite numbers"),
    (_with("mode", "radius"), r"lens_frame\.field_map: only mode 'xy' has one"),
    (_with("extra", 1), r"lens_frame: unknown field\(s\) \['extra'\]"),
    ("xy", r"lens_frame: must be an object, got str"),
])
def test_hostile_lens_frames_are_refused_naming_the_file_and_field(tmp_path, frame, field):
    cgs = trained(ScaffoldStandIn(30), modules=("lens", "display"), cond_dim=4)
    path = cgs.save(tmp_path / "a.safetensors")
    tensors, header = load_tensors(path, kind=ADAPTER_KIND, max_version=2)
    header = {k: v for k, v in header.items() if k not in ("kind", "format_version", "library_version")}
    write_raw(path, tensors, {**header, "lens_frame": frame}, kind=ADAPTER_KIND, format_version=2)
    with pytest.raises(FileFormatError, match=rf"a\.safetensors: adapter header field {field}"):
        ControlGS.load(path, cgs.unwrap())


@pytest.mark.parametrize("modules, cond_dim", [(("lens", "display"), 5), (("display",), 4)])
def test_an_xy_frame_that_does_not_fit_the_adapter_is_refused(tmp_path, modules, cond_dim):
    cgs = trained(ScaffoldStandIn(30), modules=modules, cond_dim=cond_dim)
    path = cgs.save(tmp_path / "a.safetensors")
    tensors, header = load_tensors(path, kind=ADAPTER_KIND, max_version=2)
    header = {k: v for k, v in header.items() if k not in ("kind", "format_version", "library_version")}
    write_raw(path, tensors, {**header, "lens_frame": _xy_header()}, kind=ADAPTER_KIND, format_version=2)
    with pytest.raises(FileFormatError, match=rf"a\.safetensors: adapter header field lens_frame\.mode: 'xy' needs.*"
                                              rf"cond_dim {cond_dim}"):
        ControlGS.load(path, cgs.unwrap())


def test_frame_construction_refusals_and_repr():
    with pytest.raises(InputValueError, match="mode must be one of"):
        LensFrame("polar")
    with pytest.raises(InputValueError, match="axis must be two finite numbers"):
        LensFrame("radius", (0.0, math.nan))
    with pytest.raises(InputValueError, match="field_map is for mode 'xy' only"):
        LensFrame("radius", field_map=torch.zeros(3, 3, 2))
    with pytest.raises(InputValueError, match="lens_coords needs an 'xy' lens frame"):
        LensFrame().lens_coords(torch.zeros(1, 2))
    with pytest.raises(InputValueError, match=r"samples must be an int in \[2, 257\], got 1"):
        LensFrame.from_bank(affine_bank(A, B, axis=AXIS), samples=1)
    with pytest.raises(InputValueError, match="needs the lens's field map.*a radius LensFrame"):
        LensFrame.of(LensFrame("radius", AXIS), "xy")
    xy = LensFrame.from_bank(affine_bank(A, B, axis=AXIS), samples=5)
    assert LensFrame.of(xy, "radius") == LensFrame("radius", AXIS) and LensFrame.of(xy) is xy
    assert repr(xy) == "LensFrame(mode='xy', axis=(0.25, -0.125), field_map=[5, 5, 2])"
    assert LensFrame.from_header(xy.header()) == xy and xy != LensFrame("radius", AXIS)
