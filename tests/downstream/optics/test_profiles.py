"""Tests of ``controlgs_adapter.downstream.optics.profiles``: each profile form maps display points where
the hand-computed arithmetic says, the numerical inversions round-trip, an off-centre profile is
asymmetric about the display centre and its bank's axis is its centre, the bank's optics are the
profile's chief-ray warp in every mode, the chief-ray pre-warp lands each primary of a dot where it was
rendered, the shipped examples load, and a bad file is refused naming the file and the field."""

from __future__ import annotations

import json
import math
from pathlib import Path

import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.interpolate import PchipInterpolator

from controlgs_adapter import RuntimeState
from controlgs_adapter.downstream.color import primaries_to_rgb, rgb_to_primaries
from controlgs_adapter.downstream.lens import BankMap, LensPrewarp
from controlgs_adapter.downstream.optics.profiles import (
    bank_from_profile,
    is_profile,
    load_profile,
    parse_profile,
)
from controlgs_adapter.downstream.optics.stage import PSFOptics, psf_optics
from controlgs_adapter.downstream.stage import StageContext
from controlgs_adapter.errors import FileFormatError, InputValueError

D = torch.float64
EXAMPLES = Path(__file__).resolve().parents[3] / "examples" / "lenses"
MEGANEX = [[0, 0], [10, 24.7], [20, 48.0], [30, 69.6], [35, 79.9], [40, 89.06], [45, 96.30], [48.31, 100]]


def _opencv(**over):
    base = {"kind": "opencv", "display_px": [1000, 1000], "display_mm": [50.0, 50.0], "radius_px": 500,
            "k1": 0.2, "k2": 0.05}
    base.update(over)
    return base


def _polynomial(**over):
    base = {"kind": "polynomial", "display_px": [1000, 1000], "display_mm": [40.0, 40.0], "half_fov_deg": 45.0,
            "coefficients": {"R": [1.0, 0.1], "G": [1.0, 0.1], "B": [1.0, 0.1]}}
    base.update(over)
    return base


def _table(**over):
    base = {"kind": "radial_table", "display_px": [1000, 1000], "display_mm": [24.0, 24.0], "samples": MEGANEX,
            "interpolation": "linear"}
    base.update(over)
    return base


def _at(profile, x, y):
    """``[3, 2]`` landing of one display point."""
    return profile.landing(torch.tensor(x, dtype=D), torch.tensor(y, dtype=D))


# ----------------------------------------------------------------------------- each form, by hand
def test_opencv_maps_display_to_eye_as_written_out():
    """Centre (600, 500) px on a 1000 px, 50 mm display; radius 1 = 500 px; k1 0.2, k2 0.05. Display pixel
    (850, 500) (normalised x 0.7): u = 250 / 500 = 0.5, r^2 = 0.25, factor 1 + 0.2 * 0.25 + 0.05 * 0.0625 =
    1.053125, u' = 0.5265625 -> 263.28125 px from the centre -> 863.28125 px -> 2 * 863.28125 / 1000 - 1 =
    0.7265625. The centre maps to itself; with channel scales R 0.996, B 1.014 the red and blue landings are
    0.2 + 0.996 * 0.5265625 and 0.2 + 1.014 * 0.5265625."""
    p = parse_profile(_opencv(centre_px=[600, 500], channel_scales=[0.996, 1.0, 1.014]))
    q = _at(p, 0.7, 0.0)
    assert q[:, 1].abs().max() < 1e-15
    want = torch.tensor([0.2 + 0.996 * 0.5265625, 0.7265625, 0.2 + 1.014 * 0.5265625], dtype=D)
    assert torch.allclose(q[:, 0], want, atol=1e-12, rtol=0)
    assert torch.allclose(_at(p, 0.2, 0.0), torch.tensor([0.2, 0.0], dtype=D).expand(3, 2), atol=1e-15)


def test_opencv_tangential_terms_as_written_out():
    """On the centred display, point (0.3, 0.4) normalised is u = (0.3, 0.4) (radius 1 = 500 px = half the
    width), r^2 = 0.25; with k1 = k2 = 0, p1 = 0.01, p2 = 0.02: x' = 0.3 + 2 * 0.01 * 0.12 + 0.02 * (0.25 +
    0.18) = 0.3110, y' = 0.4 + 0.01 * (0.25 + 0.32) + 2 * 0.02 * 0.12 = 0.4105."""
    p = parse_profile(_opencv(k1=0.0, k2=0.0, p1=0.01, p2=0.02))
    assert torch.allclose(_at(p, 0.3, 0.4)[1], torch.tensor([0.3110, 0.4105], dtype=D), atol=1e-12, rtol=0)
    assert not bank_from_profile(p).rotationally_symmetric


def test_polynomial_maps_display_radius_to_field_angle_as_written_out():
    """40 mm display, rho = r / 20 mm, theta = 45 deg * (rho + 0.1 rho^3). At x = 0.5 (rho 0.5): theta = 45 *
    0.5125 = 23.0625 deg; the axis slope G = d tan(theta) / dr = (pi / 4) / 20 per mm, so the landing is
    tan(23.0625 deg) / G mm = tan(23.0625 deg) / (pi / 4) normalised = 0.542098. Its half-FOV at half the
    width is 45 * 1.1 = 49.5 deg, and 45 deg per unit of output near the axis."""
    p = parse_profile(_polynomial())
    assert float(_at(p, 0.5, 0.0)[1, 0]) == pytest.approx(math.tan(math.radians(23.0625)) / (math.pi / 4), abs=1e-12)
    assert float(_at(p, 0.5, 0.0)[1, 0]) == pytest.approx(0.5420980190, abs=1e-9)
    lens = bank_from_profile(p).lens
    assert lens["half_fov_deg"] == pytest.approx(49.5, abs=1e-9)
    assert lens["deg_per_output_unit"] == pytest.approx(45.0, abs=1e-12)


def test_polynomial_eye_to_display_is_the_inverse_direction():
    """``eye_to_display``: rho = P(theta / 45 deg). theta = 22.5 deg (t = 0.5) shows at rho = 0.5125, i.e.
    display radius 10.25 mm; the axis slope is now (pi / 4) / (1 * 20) per mm as well, so display x =
    0.5125 lands at tan(22.5 deg) / (pi / 4)."""
    p = parse_profile(_polynomial(direction="eye_to_display"))
    assert float(p.field_angle_deg(torch.tensor(10.25, dtype=D))) == pytest.approx(22.5, abs=1e-9)
    assert float(_at(p, 0.5125, 0.0)[1, 0]) == pytest.approx(math.tan(math.radians(22.5)) / (math.pi / 4), abs=1e-9)


def test_radial_table_linear_is_field_angle_to_display_radius():
    """MeganeX samples on a 24 mm display, 100 % = 12 mm. Display radius 24.7 % (x = 0.247) is seen at
    10 deg; 36.35 % (halfway between 24.7 and 48.0) at 15 deg (linear). The axis slope G = (pi / 18) rad /
    (0.247 * 12 mm), so x = 0.247 lands at tan(10 deg) * 0.247 / (pi / 18) and 10 / 0.247 = 40.486 deg per
    unit of output near the axis; the half-FOV is 48.31 deg (100 %)."""
    p = parse_profile(_table())
    assert float(p.field_angle_deg(torch.tensor(0.3635 * 12, dtype=D))) == pytest.approx(15.0, abs=1e-9)
    assert float(_at(p, 0.247, 0.0)[1, 0]) == pytest.approx(math.tan(math.radians(10)) * 0.247 / (math.pi / 18), abs=1e-9)
    lens = bank_from_profile(p).lens
    assert lens["deg_per_output_unit"] == pytest.approx(10 / 0.247, abs=1e-9)
    assert lens["half_fov_deg"] == pytest.approx(48.31, abs=1e-9)


def test_radial_table_landing_goes_on_linearly_past_its_last_sample():
    """Past 100 % (12 mm, x = 1 on the axis) the landing grows by equal steps, with the slope it has just
    inside the table (a corner at 141 % stays finite, below 90 deg)."""
    p = parse_profile(_table())
    x = torch.tensor([1 - 1e-6, 1.0, 1.1, 1.2], dtype=D)
    q = p.landing(x, torch.zeros_like(x))[1, :, 0]
    inside = float(q[1] - q[0]) / 1e-6
    assert float(q[2] - q[1]) == pytest.approx(float(q[3] - q[2]), rel=1e-12)
    assert float(q[2] - q[1]) / 0.1 == pytest.approx(inside, rel=1e-4)
    assert float(p.field_angle_deg(torch.tensor(12 * math.sqrt(2), dtype=D))) < 90


def test_radial_table_monotone_cubic_matches_scipy_pchip():
    """The monotone cubic table equals SciPy's PCHIP of the same samples (display radius of an angle),
    checked by inverting at radii PCHIP gives for 40 angles."""
    p = parse_profile(_table(interpolation="monotone_cubic"))
    deg = torch.linspace(0.5, 48, 40, dtype=D)
    pchip = PchipInterpolator([s[0] for s in MEGANEX], [s[1] * 0.12 for s in MEGANEX])
    radii = torch.tensor(pchip(deg.numpy()), dtype=D)
    assert torch.allclose(p.field_angle_deg(radii), deg, atol=1e-9, rtol=0)


# ----------------------------------------------------------------------------- inversions
@settings(max_examples=25, deadline=None)
@given(k1=st.floats(0.0, 0.4), k2=st.floats(0.0, 0.2), p1=st.floats(-0.01, 0.01), cx=st.floats(-0.3, 0.3))
def test_opencv_eye_to_display_inverts_display_to_eye(k1, k2, p1, cx):
    """The same coefficients read both ways compose to the identity over the display."""
    fwd = parse_profile(_opencv(k1=k1, k2=k2, p1=p1, centre_norm=[cx, 0.1]))
    inv = parse_profile(_opencv(k1=k1, k2=k2, p1=p1, centre_norm=[cx, 0.1], direction="eye_to_display"))
    g = torch.linspace(-1, 1, 9, dtype=D)
    Y, X = torch.meshgrid(g, g, indexing="ij")
    q = fwd.landing(X, Y)[1]
    back = inv.landing(q[..., 0], q[..., 1])[1]
    assert torch.allclose(back, torch.stack([X, Y], -1), atol=1e-9, rtol=0)


def test_table_inversion_round_trips_at_every_sample_and_between():
    """Display radius of each sample angle -> its angle back; and an angle between samples -> the radius
    the linear table gives it -> the angle."""
    p = parse_profile(_table())
    for deg, pct in MEGANEX:
        assert float(p.field_angle_deg(torch.tensor(pct * 0.12, dtype=D))) == pytest.approx(deg, abs=1e-9)
    r = 0.12 * (89.06 + (96.30 - 89.06) * 0.3)
    assert float(p.field_angle_deg(torch.tensor(r, dtype=D))) == pytest.approx(41.5, abs=1e-9)


# ----------------------------------------------------------------------------- the bank
def test_off_centre_profile_is_asymmetric_and_its_axis_is_the_centre():
    """Centre at normalised (0.2, -0.1): points mirrored about it land mirrored about it; points mirrored
    about the display centre do not. The bank's axis is the centre; not rotationally symmetric."""
    p = parse_profile(_opencv(centre_norm=[0.2, -0.1]))
    c = torch.tensor([0.2, -0.1], dtype=D)
    a, b = _at(p, 0.2 + 0.6, -0.1 + 0.3), _at(p, 0.2 - 0.6, -0.1 - 0.3)
    assert torch.allclose(a - c, -(b - c), atol=1e-12)
    right, left = _at(p, 0.9, 0.0)[1, 0], _at(p, -0.9, 0.0)[1, 0]
    assert abs(float(right + left)) > 0.05
    bank = bank_from_profile(p)
    assert bank.axis == pytest.approx((0.2, -0.1)) and not bank.rotationally_symmetric and not bank.has_psf
    assert bank_from_profile(parse_profile(_opencv())).rotationally_symmetric


def test_bank_holds_the_profile_chief_rays_impulse_psfs_and_figures():
    """The chief grid is the landing at its nodes, per primary (scales: R inside B); identical maps without
    scales; the corner distortion figure is the corner's landing radius over its display radius."""
    p = parse_profile(_opencv(channel_scales=[0.99, 1.0, 1.02]))
    bank = bank_from_profile(p, grid=(9, 11))
    Y, X = torch.meshgrid(bank.chief_y.double(), bank.chief_x.double(), indexing="ij")
    assert torch.allclose(bank.chief.double(), p.landing(X, Y), atol=1e-6)
    assert bank.psf.shape[-1] == 1 and bank.chief.shape == (3, 9, 11, 2)
    corner = _at(p, 1.0, 1.0)
    want = [100 * (float(corner[c].norm()) / math.sqrt(2) - 1) for c in range(3)]
    assert bank.meta["figures"]["corner_distortion_pct"] == pytest.approx(want)
    assert want[0] < want[1] < want[2]
    plain = bank_from_profile(parse_profile(_opencv()))
    assert torch.equal(plain.chief[0], plain.chief[2])
    assert "half_fov_deg" not in plain.lens
    assert plain.meta["profile"]["k1"] == [0.2, 0.2, 0.2]


def _dot_profile():
    return parse_profile(_opencv(display_px=[40, 40], display_mm=[20.0, 20.0], radius_px=20, k1=0.12, k2=0.0,
                                 centre_norm=[0.1, -0.05], channel_scales=[0.99, 1.0, 1.015]))


def test_every_mode_is_the_chief_ray_warp_at_its_cost():
    """``exact`` and ``fast`` equal ``distortion`` exactly (and build no PSF zones); a single lit display
    pixel's light centroid, per primary, is where the profile lands the pixel's centre (to 0.03 px)."""
    p = _dot_profile()
    bank = bank_from_profile(p)
    n = 40
    img = torch.zeros(3, n, n, dtype=D)
    i, j = 27, 31
    img[:, i, j] = 1.0
    outs = {m: psf_optics(img, bank, mode=m) for m in ("distortion", "exact", "fast")}
    assert torch.equal(outs["exact"], outs["distortion"]) and torch.equal(outs["fast"], outs["distortion"])
    assert all(not rb._zones for rb in bank._cache.values())
    eye = rgb_to_primaries(outs["distortion"])
    land = _at(p, (2 * j + 1) / n - 1, (2 * i + 1) / n - 1)                    # [3, 2] normalised
    rows, cols = torch.arange(n, dtype=D) + 0.5, torch.arange(n, dtype=D) + 0.5
    s = eye.sum((1, 2))
    cx, cy = (eye.sum(1) * cols).sum(1) / s, (eye.sum(2) * rows).sum(1) / s
    assert torch.allclose(cx, (land[:, 0] + 1) * n / 2, atol=0.03) and torch.allclose(cy, (land[:, 1] + 1) * n / 2, atol=0.03)
    stage = PSFOptics(bank, mode="exact")
    assert torch.equal(stage(img, RuntimeState(), StageContext((n, n))), outs["distortion"])


def test_chief_ray_prewarp_lands_each_primary_of_a_dot_where_it_was_rendered():
    """The pre-warp for the profile's optics follows its chief rays (2 x 2 samples per display pixel): white
    dots through pre-warp then the optics land within 0.15 px per primary (measured 0.075); without the
    pre-warp the outer ones are off by more than a pixel (2.2)."""
    bank = bank_from_profile(_dot_profile())
    optics = PSFOptics(bank, mode="exact").double()
    lens = LensPrewarp.for_optics(optics, source="chief_rays", basis="rgb", supersample=2).double()
    assert isinstance(lens.map, BankMap)
    n = 40
    target = torch.zeros(3, n, n, dtype=D)
    where = [(20, 20), (8, 30), (32, 9), (30, 31), (10, 8)]
    for i, j in where:
        target[:, i, j] = 1.0
    prim = rgb_to_primaries(target)
    shown = primaries_to_rgb(lens(prim, RuntimeState(), StageContext((n, n))))
    eye = rgb_to_primaries(psf_optics(shown, bank, mode="exact"))
    plain = rgb_to_primaries(psf_optics(target, bank, mode="exact"))

    def errors(img):
        out = []
        for i, j in where:
            win = img[:, i - 4:i + 5, j - 4:j + 5].clamp_min(0)
            r, c = torch.arange(i - 4, i + 5, dtype=D), torch.arange(j - 4, j + 5, dtype=D)
            s = win.sum((1, 2))
            out.append(torch.hypot((win.sum(2) * r).sum(1) / s - i, (win.sum(1) * c).sum(1) / s - j))
        return torch.stack(out)

    assert float(errors(eye).max()) < 0.15
    assert float(errors(plain).max()) > 1.0


# ----------------------------------------------------------------------------- files
@pytest.mark.parametrize("path", sorted(EXAMPLES.glob("*.json")), ids=lambda p: p.name)
def test_shipped_example_profiles_load_and_make_banks(path):
    obj = json.loads(path.read_text())
    assert is_profile(obj)
    profile = load_profile(path)
    bank = bank_from_profile(profile)
    assert bank.lens["kind"] == "profile" and not bank.has_psf
    assert bank.axis == pytest.approx(profile.centre)
    bank.resample_to(24, 24)                                                      # the map does not fold


def test_examples_cover_every_form_and_an_off_centre_eye():
    kinds = {load_profile(p).kind for p in EXAMPLES.glob("*.json")}
    assert kinds == {"opencv", "polynomial", "radial_table"}
    assert any(load_profile(p).centre != (0.0, 0.0) for p in EXAMPLES.glob("*.opencv.json"))


def test_is_profile():
    assert is_profile(_opencv()) and is_profile(_table())
    assert not is_profile({"surfaces": []}) and not is_profile({"kind": "psf_bank"}) and not is_profile([1])


BAD = [
    ("missing k1", lambda: {k: v for k, v in _opencv().items() if k != "k1"}, "'k1'"),
    ("NaN", lambda: _opencv(k2=float("nan")), "'k2'"),
    ("non-monotone table", lambda: _table(samples=[[0, 0], [10, 30], [20, 25]]), "'samples'"),
    ("table not from the axis", lambda: _table(samples=[[1, 0], [10, 30]]), "'samples'"),
    ("negative size", lambda: _opencv(display_mm=[-50.0, 50.0]), "'display_mm'"),
    ("fractional pixels", lambda: _opencv(display_px=[1000.5, 1000]), "'display_px'"),
    ("unknown kind", lambda: _opencv(kind="bezier"), "'kind'"),
    ("unknown field", lambda: _opencv(k4=0.1), "'k4'"),
    ("centre outside", lambda: _opencv(centre_norm=[1.2, 0.0]), "'centre_norm'"),
    ("two centres", lambda: _opencv(centre_norm=[0.0, 0.0], centre_px=[500, 500]), "'centre_norm'"),
    ("folding k1", lambda: _opencv(k1=-0.6), "'k1'"),
    ("bad direction", lambda: _opencv(direction="forward"), "'direction'"),
    ("per-primary length", lambda: _opencv(k1=[0.1, 0.2]), "'k1'"),
    ("polynomial past 90 deg", lambda: _polynomial(half_fov_deg=80.0), "'coefficients'"),
    ("bad scales", lambda: _opencv(channel_scales=[1.0, 0.0, 1.0]), "'channel_scales'"),
    ("a string size", lambda: _opencv(radius_px="500"), "'radius_px'"),
]


@pytest.mark.parametrize("what, make, field", BAD, ids=[b[0] for b in BAD])
def test_bad_profiles_are_refused_naming_file_and_field(tmp_path, what, make, field):
    path = tmp_path / "eye.json"
    path.write_text(json.dumps(make()))                                           # NaN is written as the NaN literal
    with pytest.raises(FileFormatError) as e:
        load_profile(path)
    msg = str(e.value)
    assert str(path) in msg and field in msg and "\n" not in msg, msg
    with pytest.raises(InputValueError, match=field.replace("'", "")):
        parse_profile(make(), "eye")


def test_unreadable_and_oversized_files(tmp_path):
    with pytest.raises(FileFormatError, match="not JSON"):
        (tmp_path / "a.json").write_text("{kind: opencv")
        load_profile(tmp_path / "a.json")
    with pytest.raises(FileFormatError, match="at most"):
        (tmp_path / "b.json").write_text(" " * (1 << 20 + 1))
        load_profile(tmp_path / "b.json")
    with pytest.raises(FileFormatError, match="'kind'"):
        (tmp_path / "c.json").write_text("[1, 2]")
        load_profile(tmp_path / "c.json")


def test_the_default_prewarp_of_a_profile_is_its_chief_rays_without_a_warning(recwarn):
    """A bank without PSFs has nothing to fit: ``for_optics``'s default is its chief-ray map at 2 x 2 samples per
    display pixel, the same stage as asked for explicitly, and no 'no fitted pre-warp LUT' warning."""
    bank = bank_from_profile(_dot_profile())
    optics = PSFOptics(bank, mode="exact")
    default = LensPrewarp.for_optics(optics)
    explicit = LensPrewarp.for_optics(optics, source="chief_rays", supersample=2)
    assert not [w for w in recwarn if "pre-warp" in str(w.message)]
    img = torch.rand(1, 3, 24, 24, generator=torch.Generator().manual_seed(0))
    ctx = StageContext((24, 24))
    assert isinstance(default.map, BankMap) and torch.equal(default(img, RuntimeState(), ctx), explicit(img, RuntimeState(), ctx))
