"""Images of any aspect on the headset display (downstream/placement.py): the region, the optics,
the lens pre-warp built from the bank and the per-anchor strengths all use the same placement."""

from __future__ import annotations

import math

import pytest
import torch

from controlgs_adapter import ControlGS, RuntimeState
from controlgs_adapter.downstream.color import primaries_to_rgb, rgb_to_primaries
from controlgs_adapter.downstream.lens import CARDBOARD_RADIAL, LensPrewarp
from controlgs_adapter.downstream.pipeline import Pipeline
from controlgs_adapter.downstream.placement import image_region, to_display
from controlgs_adapter.downstream.stage import StageContext
from controlgs_adapter.errors import InputValueError

from scaffold_standin import ScaffoldStandIn, make_camera

optics_mod = pytest.importorskip("controlgs_adapter.downstream.optics.stage")
from controlgs_adapter.downstream.optics.bank import PSFBank  # noqa: E402

STATE = RuntimeState()


# ----------------------------------------------------------------------------- the region, by hand
@pytest.mark.parametrize("h, w, half, pitch, size", [
    (1080, 1920, (1.0, 0.5625), (0.0125, 0.0125), (24.0, 13.5)),      # 16:9 landscape: full width
    (1920, 1080, (0.5625, 1.0), (0.0125, 0.0125), (13.5, 24.0)),      # 9:16 portrait: full height
    (27, 48, (1.0, 0.5625), (0.5, 0.5), (24.0, 13.5)),
    (48, 48, (1.0, 1.0), (0.5, 0.5), (24.0, 24.0)),                    # square: the whole display
    (30, 40, (1.0, 0.75), (0.6, 0.6), (24.0, 18.0)),
])
def test_fit_region_by_hand(h, w, half, pitch, size):
    r = image_region(h, w)
    assert (r.half_x, r.half_y) == pytest.approx(half, abs=1e-15)
    assert r.pitch_mm == pytest.approx(pitch, abs=1e-15) and r.size_mm == pytest.approx(size, abs=1e-12)
    assert r.bounds_mm == pytest.approx((-size[0] / 2, size[0] / 2, -size[1] / 2, size[1] / 2))
    # the region in mm and in normalised display coordinates agree (display half-width 12 mm)
    assert (r.size_mm[0] / 24, r.size_mm[1] / 24) == pytest.approx((r.half_x, r.half_y))


def test_square_images_span_the_display_exactly_and_stretch_is_anisotropic():
    for n in (7, 27, 48, 1000):
        r = image_region(n, n)
        assert (r.half_x, r.half_y) == (1.0, 1.0) and r.pitch_mm == (24 / n, 24 / n)
    s = image_region(1080, 1920, placement="stretch")
    assert (s.half_x, s.half_y) == (1.0, 1.0) and s.pitch_mm == pytest.approx((24 / 1920, 24 / 1080))
    # a non-square display: a square image is limited by the shorter side (30 x 20 mm: pitch 2 mm)
    r = image_region(10, 10, (30.0, 20.0))
    assert r.pitch_mm == (2.0, 2.0) and (r.half_x, r.half_y) == pytest.approx((20 / 30, 1.0))
    xy = torch.tensor([[1.0, -1.0], [0.5, 0.25]])
    assert torch.equal(to_display(xy, 27, 48), torch.tensor([[1.0, -0.5625], [0.5, 0.140625]]))
    with pytest.raises(InputValueError, match="placement"):
        image_region(4, 4, placement="crop")  # type: ignore[arg-type]


# ----------------------------------------------------------------------------- square: bit-identical
@pytest.mark.parametrize("n", [27, 32])
def test_square_images_are_bit_identical_to_the_stretched_display(n):
    bank = PSFBank.default()
    fit = bank.resample_to(n, n, dtype=torch.float64)
    old = bank.resample_to(n, n, dtype=torch.float64, placement="stretch")
    assert fit is not old
    for name in ("field_index", "field_weight", "splat_index", "splat_weight", "kernels"):
        assert torch.equal(getattr(fit, name), getattr(old, name)), name
    x = torch.rand(3, n, n, dtype=torch.float64, generator=torch.Generator().manual_seed(n))
    for mode in ("distortion", "exact"):
        assert torch.equal(optics_mod.psf_optics(x, bank, mode), optics_mod.psf_optics(x, bank, mode, placement="stretch"))
    a = LensPrewarp.from_psf_bank(bank, (n, n), gain="jacobian").map((n, n), torch.float32, torch.device("cpu"))
    b = LensPrewarp.from_chief_ray_map(bank.chief, (n, n), sample_x=bank.chief_x, sample_y=bank.chief_y,
                                       gain="jacobian").map((n, n), torch.float32, torch.device("cpu"))
    assert torch.equal(a[0], b[0]) and torch.equal(a[1], b[1])


def test_fit_samples_the_bank_at_the_pixels_display_positions():
    """16:9 under "fit": a 27 x 48 image's pixel corners sit at display-normalised
    ``(x, 9/16 y)``; each pixel's footprint is the quad of its corners' chief-ray images, computed
    here by hand from the bank's chief rays (the 48 x 48 image's map, landing points divided by
    the half-extents): its overlap areas add up to the quad's area and sit on the quad;
    the PSFs use the square pixel pitch."""
    bank = PSFBank.default()
    wide, square = bank.resample_to(27, 48, dtype=torch.float64), bank.resample_to(48, 48, dtype=torch.float64)
    ue = torch.linspace(-1, 1, 49, dtype=torch.float64)
    ve = torch.linspace(-1, 1, 28, dtype=torch.float64)
    V, U = torch.meshgrid(ve, ue, indexing="ij")
    ch = square._chief_at(U, V * 27 / 48)                                    # [L, 28, 49, 2]
    X = (ch[..., 0] + 1) * 24 + wide.m
    Y = (ch[..., 1] * 48 / 27 + 1) * 13.5 + wide.m
    qx = torch.stack([X[:, :-1, :-1], X[:, :-1, 1:], X[:, 1:, 1:], X[:, 1:, :-1]]).reshape(4, 3, -1)
    qy = torch.stack([Y[:, :-1, :-1], Y[:, :-1, 1:], Y[:, 1:, 1:], Y[:, 1:, :-1]]).reshape(4, 3, -1)
    cross = [qx[e] * qy[(e + 1) % 4] - qx[(e + 1) % 4] * qy[e] for e in range(4)]
    area = 0.5 * sum(cross)
    cx = sum((qx[e] + qx[(e + 1) % 4]) * cross[e] for e in range(4)) / (6 * area)
    cy = sum((qy[e] + qy[(e + 1) % 4]) * cross[e] for e in range(4)) / (6 * area)
    idx, w = wide.splat_index, wide.splat_weight                             # [L, J, N] (radiance: areas)
    col, row = (idx % wide.Wc).double() + 0.5, (idx // wide.Wc).double() + 0.5
    assert torch.allclose(w.sum(1), area, atol=1e-12)
    assert torch.allclose(wide.area, area, atol=1e-12)
    # first moments by pixel-centre quadrature of the overlaps: within a tenth of a pixel
    assert ((w * col).sum(1) / area - cx).abs().max() < 0.1
    assert ((w * row).sum(1) / area - cy).abs().max() < 0.1
    assert torch.equal(wide.kernels, square.kernels)       # pitch 0.5 mm in both


@pytest.mark.parametrize("h, w, axis", [(54, 96, -2), (96, 54, -1)])
@pytest.mark.parametrize("mode", ["distortion", "exact"])
def test_fit_simulates_the_image_region_of_a_black_display(h, w, axis, mode):
    """Only the image's region is simulated and the rest of the display is black: the optics of a
    16:9 (9:16) image equals, inside its band, the optics of the square image that holds it in the
    display's central band and black elsewhere (same pixel pitch)."""
    n = max(h, w)
    x = torch.rand(3, h, w, dtype=torch.float64, generator=torch.Generator().manual_seed(1))
    big = torch.zeros(3, n, n, dtype=torch.float64)
    band = [slice(None)] * 3
    band[axis] = slice((n - min(h, w)) // 2, (n + min(h, w)) // 2)
    big[tuple(band)] = x
    bank = PSFBank.default()
    got = optics_mod.psf_optics(x, bank, mode)
    want = optics_mod.psf_optics(big, bank, mode)[tuple(band)]
    assert torch.allclose(got, want, rtol=0, atol=1e-12)


# ----------------------------------------------------------------------------- pre-warp then optics
DOTS = ((0.0, 0.0), (0.6, 0.5), (-0.6, -0.5), (0.75, -0.6), (-0.45, 0.7), (0.85, 0.0), (0.0, -0.8))


def _dots(h: int, w: int) -> tuple[torch.Tensor, list[tuple[int, int]]]:
    img = torch.zeros(3, h, w, dtype=torch.float64)
    where = []
    for x, y in DOTS:
        i, j = int((y + 1) / 2 * h), int((x + 1) / 2 * w)
        img[:, i, j] = 1.0
        where.append((i, j))
    return img, where


def _centroids(img: torch.Tensor, where: list[tuple[int, int]], r: int = 4) -> torch.Tensor:
    """``[dots, 3, 2]`` (row, col) light centroid of each primary in a window around each dot."""
    out = []
    for i, j in where:
        win = img[:, max(i - r, 0):i + r + 1, max(j - r, 0):j + r + 1].clamp_min(0)
        rows = torch.arange(max(i - r, 0), max(i - r, 0) + win.shape[1], dtype=img.dtype)
        cols = torch.arange(max(j - r, 0), max(j - r, 0) + win.shape[2], dtype=img.dtype)
        s = win.sum((1, 2))
        out.append(torch.stack([(win.sum(2) * rows).sum(1) / s, (win.sum(1) * cols).sum(1) / s], -1))
    return torch.stack(out)


@pytest.mark.parametrize("h, w", [(48, 48), (27, 48), (48, 27)])
def test_prewarp_then_optics_lands_dots_where_they_started(h, w):
    """The pipeline's lens (built from the optics' bank for the same region), then the optics'
    chief-ray warp: each white dot is seen where it was rendered, to a fraction of a pixel."""
    p = Pipeline.from_config({"lens": {"source": "chief_rays", "basis": "rgb"}, "optics": {"mode": "distortion"}}).double()
    target, where = _dots(h, w)
    prim = rgb_to_primaries(target)                 # the optics is separable per primary: warp in that domain
    shown = primaries_to_rgb(p["lens"](prim, STATE, StageContext((h, w))))
    eye = rgb_to_primaries(optics_mod.psf_optics(shown, p["optics"].bank, mode="distortion"))
    plain = rgb_to_primaries(optics_mod.psf_optics(target, p["optics"].bank, mode="distortion"))
    want = torch.tensor(where, dtype=torch.float64)[:, None, :]
    err = (_centroids(eye, where) - want).norm(dim=-1)          # [dots, 3]
    moved = (_centroids(plain, where) - want).norm(dim=-1)
    assert float(err.max()) < 0.25, err                          # the same as for a square image
    assert float(moved.max()) > 0.8                              # without the pre-warp the outer dots move


def test_a_prewarp_for_the_wrong_region_misses():
    """Sensitivity of the dot test: a pre-warp built as if the 27 x 48 image spanned the display
    (stretch) does not land the dots under the "fit" optics."""
    bank = PSFBank.default()
    target, where = _dots(27, 48)
    prim = rgb_to_primaries(target)
    wrong = LensPrewarp.from_psf_bank(bank, placement="stretch").double()
    wrong.basis = "rgb"  # applied to primaries below
    eye = rgb_to_primaries(optics_mod.psf_optics(primaries_to_rgb(wrong(prim, STATE, StageContext((27, 48)))), bank,
                                             mode="distortion"))
    err = (_centroids(eye, where) - torch.tensor(where, dtype=torch.float64)[:, None, :]).norm(dim=-1)
    assert float(err.max()) > 0.3


def test_the_pipeline_lens_follows_the_optics_placement():
    p = Pipeline.from_config({"lens": True, "optics": {"mode": "distortion", "placement": "stretch"}})
    assert p["optics"].placement == "stretch" and p["lens"].map.placement == "stretch"
    bank = p["optics"].bank
    for size in ((27, 48), (48, 27), (40, 40)):
        grid, gain = Pipeline.from_config({"lens": {"source": "chief_rays"}, "optics": True})["lens"].map(
            size, torch.float32, torch.device("cpu"))
        lut = LensPrewarp.from_psf_bank(bank, size).map(size, torch.float32, torch.device("cpu"))[0]
        assert gain is None and torch.allclose(grid, lut, atol=1e-6)


def test_the_analytic_radial_map_uses_the_fit_frame():
    """RadialMap's aspect-corrected radius is the display radius under "fit", computed here in mm:
    pixel (i, j) of a 27 x 48 image sits at ((j + 0.5) 0.5 - 12, (i + 0.5) 0.5 - 6.75) mm."""
    k1 = torch.tensor([c[0] for c in CARDBOARD_RADIAL], dtype=torch.float64)
    for h, w in ((27, 48), (48, 27)):
        grid = LensPrewarp().map((h, w), torch.float64, torch.device("cpu"))[0]        # [3, H, W, 2]
        i, j = torch.meshgrid(torch.arange(h, dtype=torch.float64), torch.arange(w, dtype=torch.float64), indexing="ij")
        x_mm, y_mm = (j + 0.5) * 0.5 - w / 4, (i + 0.5) * 0.5 - h / 4
        r2 = (x_mm ** 2 + y_mm ** 2) / 12.0 ** 2                   # display half-width 12 mm
        p = torch.stack([x_mm / (w / 4), y_mm / (h / 4)], -1)      # image-normalised
        want = p[None] * (1 + k1[:, None, None] * r2)[..., None]
        assert torch.allclose(grid, want, atol=1e-6)


# ----------------------------------------------------------------------------- gradients, flat field
@pytest.mark.parametrize("mode", ["distortion", "exact"])
def test_gradcheck_optics_on_a_non_square_image(mode):
    bank = PSFBank.default()
    x = (torch.rand(3, 5, 9, dtype=torch.float64, generator=torch.Generator().manual_seed(0)) + 0.1).requires_grad_(True)
    assert torch.autograd.gradcheck(lambda t: optics_mod.psf_optics(t, bank, mode), (x,))


def test_flat_field_through_the_pipeline_is_smooth_for_16_9():
    """Lens pre-warp + exact PSF optics on a flat 16:9 field: finite, symmetric, and no rougher than
    the same display band of a square image (the shading is the lens's smooth fall-off: its second
    difference is the square image's to 1e-12, no seam)."""
    p = Pipeline.from_config({"lens": True, "optics": {"mode": "exact"}}).double()
    eye = p(torch.full((3, 54, 96), 0.5, dtype=torch.float64), STATE)
    square = p(torch.full((3, 96, 96), 0.5, dtype=torch.float64), STATE)
    assert torch.isfinite(eye).all()

    def rough(img: torch.Tensor, m: int = 6) -> float:
        inner = img[:, m:-m, m:-m]
        d2x = (inner[..., 2:] - 2 * inner[..., 1:-1] + inner[..., :-2]).abs().max()
        d2y = (inner[:, 2:] - 2 * inner[:, 1:-1] + inner[:, :-2]).abs().max()
        return float(max(d2x, d2y))

    assert rough(eye) <= rough(square) + 1e-12 and rough(eye) < 7e-3
    assert torch.allclose(eye, eye.flip(-1), atol=1e-5) and torch.allclose(eye, eye.flip(-2), atol=1e-5)
    assert torch.allclose(eye[:, 27], square[:, 48], atol=1e-3)     # the display's horizontal axis


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


def test_optics_stage_placement_argument():
    assert optics_mod.PSFOptics().placement == "fit"
    with pytest.warns(DeprecationWarning, match="placement"):
        assert optics_mod.PSFOptics(stretch=True).placement == "stretch"
    with pytest.raises(InputValueError, match="placement"):
        optics_mod.PSFOptics(placement="crop")  # type: ignore[arg-type]
    with pytest.raises(InputValueError, match="size"):
        LensPrewarp.from_psf_bank(None, gain=torch.ones(3, 4, 4))
