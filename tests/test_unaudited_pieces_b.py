"""By-hand checks of lens pre-warp pieces no other test pins: LUT resizing (interpolation and
linear extrapolation), the learned map's output layout, Newton inversion, chief-ray grids, the
bank fingerprint, and the foveation placeholder."""

from __future__ import annotations

import copy

import pytest
import torch

from controlgs_adapter.downstream.color import convert_domain, linear_to_srgb, srgb_to_linear
from controlgs_adapter.downstream.foveation import Foveation, foveation
from controlgs_adapter.downstream.lens import (
    DisplayLUTMap, LensPrewarp, LUTMap, MLPMap, bank_fingerprint, chief_ray_grid, invert_map, pixel_grid,
)
from controlgs_adapter.downstream.optics.operators import psf_fast, psf_reference
from controlgs_adapter.downstream.pipeline import Pipeline
from controlgs_adapter.downstream.stage import Stage, StageContext
from controlgs_adapter.errors import InputValueError, ShapeError
from controlgs_adapter.state import RuntimeState
from test_optics_operators import synthetic_bank

CPU = torch.device("cpu")
# per channel c: F_c(x, y) = (a0 + a1 x + a2 y + a3 x y, b0 + b1 x + b2 y + b3 x y)
_COEF = torch.tensor([
    [[0.05, 1.10, 0.10, 0.20], [-0.02, 0.05, 0.90, -0.10]],
    [[-0.03, 0.95, -0.05, 0.00], [0.04, 0.02, 1.05, 0.15]],
    [[0.00, 1.20, 0.00, -0.05], [0.01, -0.10, 1.15, 0.00]],
], dtype=torch.float64)  # [3, 2 (out x, y), 4]


def _bilinear_field(p: torch.Tensor, coef: torch.Tensor = _COEF) -> torch.Tensor:
    """``coef`` ``[3, D, 4]`` evaluated at points ``p`` ``[H, W, 2]`` -> ``[3, H, W, D]`` (float64)."""
    x, y = p[..., 0].double(), p[..., 1].double()
    basis = torch.stack([torch.ones_like(x), x, y, x * y], -1)  # [H, W, 4]
    return torch.einsum("cdk,hwk->chwd", coef, basis)


# --- LUTMap -------------------------------------------------------------------------------------

@pytest.mark.parametrize("size", [(7, 5), (2, 9), (4, 3)])
def test_lut_map_interpolates_and_extrapolates_a_bilinear_table_exactly(size):
    """Bilinear interpolation reproduces a bilinear function exactly, and so does linear
    extrapolation past the table's outer pixel centres (the border pixels of a larger image)."""
    table_size = (4, 3)
    grid = _bilinear_field(pixel_grid(table_size, torch.float64))  # [3, 4, 3, 2]
    gain_coef = torch.tensor([[[1.0, 0.2, -0.1, 0.05]], [[0.8, 0.0, 0.3, 0.0]], [[1.2, -0.2, 0.0, 0.1]]],
                             dtype=torch.float64)
    gain = _bilinear_field(pixel_grid(table_size, torch.float64), gain_coef)[..., 0]  # [3, 4, 3]
    got_grid, got_gain = LUTMap(grid, gain)(size, torch.float64, CPU)
    p = pixel_grid(size, torch.float64)
    assert got_grid.shape == (3, *size, 2) and got_gain.shape == (3, *size)
    assert torch.allclose(got_grid, _bilinear_field(p), atol=1e-6, rtol=0)  # buffers are float32
    assert torch.allclose(got_gain, _bilinear_field(p, gain_coef)[..., 0], atol=1e-6, rtol=0)


def test_lut_map_same_size_returns_the_table_and_no_gain_means_one():
    g = torch.Generator().manual_seed(3)
    grid = pixel_grid((3, 4), torch.float64) + 0.1 * torch.rand(3, 3, 4, 2, dtype=torch.float64, generator=g)
    out_grid, out_gain = LUTMap(grid)((3, 4), torch.float64, CPU)
    assert torch.allclose(out_grid, grid, atol=1e-7, rtol=0)
    assert torch.equal(out_gain, torch.ones(3, 3, 4, dtype=torch.float64))
    assert out_grid.dtype == torch.float64
    assert LUTMap(grid)((3, 4), torch.float32, CPU)[0].dtype == torch.float32


def test_lut_map_is_identity_follows_its_buffers():
    ident = pixel_grid((3, 3), torch.float64).expand(3, -1, -1, -1).clone()
    m = LUTMap(ident)
    assert m.is_identity()
    m.gain[1, 2, 0] = 1.5  # in-place edit after the first answer
    assert not m.is_identity()
    m.gain[1, 2, 0] = 1.0
    assert m.is_identity()
    m.displacement[0, 0, 0, 1] = 1e-3
    assert not m.is_identity()
    assert not LUTMap(ident, torch.full((3, 3, 3), 2.0, dtype=torch.float64)).is_identity()


def test_lut_map_refusals_name_the_argument():
    with pytest.raises(ShapeError, match="grid needs at least 2x2"):
        LUTMap(torch.zeros(3, 1, 4, 2))
    with pytest.raises(ShapeError, match="grid needs at least 2x2"):
        LUTMap(torch.zeros(3, 4, 1, 2))
    with pytest.raises(ShapeError, match="gain"):
        LUTMap(torch.zeros(3, 2, 2, 2), torch.ones(3, 2, 3))
    with pytest.raises(ShapeError, match="grid"):
        LUTMap(torch.zeros(2, 2, 2, 2))


# --- MLPMap -------------------------------------------------------------------------------------

def test_mlp_map_output_layout_by_hand():
    """With a zero last weight the output is the bias: channel c reads (dx, dy, log gain) from
    bias[3c : 3c + 3]."""
    m = MLPMap(hidden=5, layers=2, frequencies=1).double()
    assert m.is_identity()
    bias = torch.tensor([0.1, -0.2, 0.3, 0.0, 0.05, -0.4, -0.1, 0.0, 0.7], dtype=torch.float64)
    with torch.no_grad():
        m.mlp[-1].bias.copy_(bias)
    assert not m.is_identity()
    grid, gain = m((3, 4), torch.float64, CPU)
    p = pixel_grid((3, 4), torch.float64)
    b = bias.reshape(3, 3)
    for c in range(3):
        assert torch.allclose(grid[c], p + b[c, :2], atol=1e-15)
        assert torch.allclose(gain[c], torch.full((3, 4), float(torch.exp(b[c, 2])), dtype=torch.float64), atol=1e-15)
    with torch.no_grad():
        m.mlp[-1].bias.zero_()
        m.mlp[-1].weight[4, 0] = 1e-3
    assert not m.is_identity()


def test_mlp_map_fourier_features_by_hand():
    m = MLPMap(hidden=3, layers=3, frequencies=2)
    assert m.mlp[0].in_features == 2 + 4 * 2
    assert [type(x).__name__ for x in m.mlp] == ["Linear", "SiLU"] * 3 + ["Linear"]
    assert m.mlp[2].in_features == 3 and m.mlp[-1].out_features == 9
    p = torch.tensor([[0.25, -0.5]], dtype=torch.float64)
    x, y = 0.25, -0.5
    pi = torch.pi
    ang = torch.tensor([pi * x, 2 * pi * x, pi * y, 2 * pi * y], dtype=torch.float64)
    want = torch.cat([torch.tensor([x, y], dtype=torch.float64), ang.sin(), ang.cos()])
    assert torch.allclose(m._encode(p)[0], want, atol=1e-15)
    raw = MLPMap(hidden=3, layers=1, frequencies=0)
    assert raw.mlp[0].in_features == 2 and torch.equal(raw._encode(p), p)


@pytest.mark.parametrize("kwargs", [dict(hidden=0), dict(layers=0), dict(frequencies=-1)])
def test_mlp_map_refuses_bad_sizes(kwargs):
    with pytest.raises(InputValueError, match="hidden, layers must be >= 1 and frequencies >= 0"):
        MLPMap(**kwargs)


def test_mlp_map_accepts_the_bounds():
    m = MLPMap(hidden=1, layers=1, frequencies=0)
    assert m.is_identity() and m((2, 2), torch.float32, CPU)[0].shape == (3, 2, 2, 2)


# --- invert_map / chief_ray_grid ---------------------------------------------------------------

def _affine(a: torch.Tensor, t: torch.Tensor, p: torch.Tensor) -> torch.Tensor:
    """Per channel ``a[c] @ p + t[c]``: ``a`` ``[3, 2, 2]``, ``t`` ``[3, 2]``, ``p`` ``[H, W, 2]`` -> ``[3, H, W, 2]``."""
    return torch.einsum("cij,hwj->chwi", a, p) + t[:, None, None, :]


_A = torch.tensor([[[1.2, 0.1], [-0.05, 0.9]], [[0.8, 0.0], [0.0, 1.1]], [[1.0, -0.2], [0.15, 1.05]]], dtype=torch.float64)
_T = torch.tensor([[0.05, -0.1], [0.0, 0.02], [-0.07, 0.03]], dtype=torch.float64)


def test_invert_map_of_an_affine_map_on_custom_samples():
    """F_c affine on samples running -1 .. 1 (edges, not cell centres): G_c = A_c^-1 (q - t_c)."""
    sx, sy = torch.linspace(-1, 1, 5, dtype=torch.float64), torch.linspace(-1, 1, 4, dtype=torch.float64)
    p = torch.stack(torch.meshgrid(sx, sy, indexing="xy"), -1)  # [4, 5, 2]
    fmap = _affine(_A, _T, p)
    q = pixel_grid((6, 7), torch.float64)
    want = _affine(torch.linalg.inv(_A), -torch.einsum("cij,cj->ci", torch.linalg.inv(_A), _T), q)
    got = invert_map(fmap, (6, 7), sample_x=sx, sample_y=sy)
    assert got.shape == (3, 6, 7, 2) and got.dtype == torch.float64
    assert torch.allclose(got, want, atol=1e-9, rtol=0)
    assert invert_map(fmap.float(), (6, 7), sample_x=sx, sample_y=sy).dtype == torch.float32


def test_invert_map_without_iterations_is_the_first_order_start():
    """No Newton step (iterations=0, or a tolerance every residual meets): G = 2 q - F(q)."""
    a = torch.eye(2, dtype=torch.float64).expand(3, 2, 2) * 1.25
    fmap = _affine(a, torch.zeros(3, 2, dtype=torch.float64), pixel_grid((3, 3), torch.float64))
    q = pixel_grid((4, 5), torch.float64)
    start = (2.0 - 1.25) * q.expand(3, -1, -1, -1)
    assert torch.allclose(invert_map(fmap, (4, 5), iterations=0), start, atol=1e-12)
    assert torch.allclose(invert_map(fmap, (4, 5), tol=10.0), start, atol=1e-12)
    assert torch.allclose(invert_map(fmap, (4, 5)), q.expand(3, -1, -1, -1) / 1.25, atol=1e-9)


def test_invert_map_refusals():
    with pytest.raises(InputValueError, match="not invertible"):
        invert_map(torch.full((3, 3, 3, 2), 0.3, dtype=torch.float64), (2, 2))  # constant: zero Jacobian
    with pytest.raises(ShapeError, match="forward_map needs at least 2x2"):
        invert_map(torch.zeros(3, 2, 1, 2), (2, 2))
    with pytest.raises(ShapeError, match="forward_map"):
        invert_map(torch.zeros(2, 2, 2, 2), (2, 2))
    fmap = pixel_grid((3, 3), torch.float64).expand(3, -1, -1, -1)
    with pytest.raises(InputValueError, match="sample_y must be uniformly spaced"):
        invert_map(fmap, (2, 2), sample_y=torch.tensor([-1.0, -0.9, 1.0], dtype=torch.float64))
    with pytest.raises(ShapeError, match="sample_x"):
        invert_map(fmap, (2, 2), sample_x=torch.linspace(-1, 1, 4, dtype=torch.float64))


def test_chief_ray_grid_display_to_eye_and_jacobian_gain_of_an_affine_map():
    sx, sy = torch.linspace(-1.2, 1.2, 4, dtype=torch.float64), torch.linspace(-1, 1, 3, dtype=torch.float64)
    chief = _affine(_A, _T, torch.stack(torch.meshgrid(sx, sy, indexing="xy"), -1))
    size = (5, 6)
    grid, gain = chief_ray_grid(chief, size, sample_x=sx, sample_y=sy)
    assert gain is None
    assert torch.allclose(grid, _affine(_A, _T, pixel_grid(size, torch.float64)), atol=1e-12, rtol=0)
    _, jac = chief_ray_grid(chief, size, sample_x=sx, sample_y=sy, gain="jacobian")
    assert jac is not None
    det = torch.linalg.det(_A).abs()  # constant area magnification of an affine map
    assert torch.allclose(jac, det[:, None, None].expand(3, *size), atol=1e-12)
    given = torch.rand(3, *size, dtype=torch.float64)
    assert chief_ray_grid(chief, size, sample_x=sx, sample_y=sy, gain=given)[1] is given


def test_chief_ray_grid_eye_to_display_inverts():
    sx = torch.linspace(-1, 1, 4, dtype=torch.float64)
    chief = _affine(_A, _T, torch.stack(torch.meshgrid(sx, sx, indexing="xy"), -1))
    grid, _ = chief_ray_grid(chief, (4, 4), direction="eye_to_display", sample_x=sx, sample_y=sx)
    back = torch.einsum("cij,chwj->chwi", _A, grid) + _T[:, None, None, :]  # F_c(G_c(q))
    assert torch.allclose(back, pixel_grid((4, 4), torch.float64).expand(3, -1, -1, -1), atol=1e-9)


def test_chief_ray_grid_refusals():
    ok = pixel_grid((3, 3), torch.float64).expand(3, -1, -1, -1)
    with pytest.raises(ShapeError, match="chief_ray_map needs at least 2x2"):
        chief_ray_grid(torch.zeros(3, 3, 1, 2), (2, 2))
    with pytest.raises(InputValueError, match="direction must be"):
        chief_ray_grid(ok, (2, 2), direction="up")  # type: ignore[arg-type]
    with pytest.raises(InputValueError, match="gain must be a tensor, 'jacobian' or None"):
        chief_ray_grid(ok, (2, 2), gain="area")  # type: ignore[arg-type]


# --- bank_fingerprint ---------------------------------------------------------------------------

def test_bank_fingerprint_tracks_every_optics_field():
    from controlgs_adapter.downstream.optics.bank import PSFBank

    bank = PSFBank.default()
    fp = bank_fingerprint(bank)
    assert len(fp) == 16 and all(ch in "0123456789abcdef" for ch in fp)
    # copies bypass __init__: PSFBank renormalises its PSFs there, which moves float32 rounding
    def with_fields(**fields: object) -> PSFBank:
        other = copy.copy(bank)
        other._cache = {}  # not shared with the process-wide default bank
        for name, value in fields.items():
            setattr(other, name, value)
        return other

    same = with_fields(psf=bank.psf.clone(), chief=bank.chief.clone(), meta={"other": 1})
    assert bank_fingerprint(same) == fp  # same numbers, other metadata
    changed = {
        "psf": bank.psf.flip(-1), "psf_pitch_mm": bank.psf_pitch_mm * 1.01, "field_x": bank.field_x * 0.99,
        "field_y": bank.field_y * 0.99, "chief": bank.chief * 1.001, "chief_x": bank.chief_x * 0.99,
        "chief_y": bank.chief_y * 0.99, "wavelengths_nm": tuple(w + 1 for w in bank.wavelengths_nm),
        "display_mm": (bank.display_mm[0] + 1, bank.display_mm[1]),
    }
    fps = {name: bank_fingerprint(with_fields(**{name: value})) for name, value in changed.items()}
    assert all(v != fp for v in fps.values()), fps
    assert len(set(fps.values())) == len(fps)


# --- foveation, pipeline ------------------------------------------------------------------------

_CALLS: list[str] = []  # names of the _Scale stages processed, in call order


class _Scale(Stage):
    """A stage multiplying by ``factor`` in its domain; the identity (skipped) when factor is 1."""

    name = "scale"
    domain = "linear"
    order = 15.0

    def __init__(self, factor: float = 2.0) -> None:
        super().__init__()
        self.factor = factor

    def is_identity(self, state: RuntimeState, ctx: StageContext | None = None) -> bool:
        return self.factor == 1.0

    def process(self, image: torch.Tensor, state: RuntimeState, ctx: StageContext) -> torch.Tensor:
        _CALLS.append(self.name)
        return image * self.factor


def _stage(name: str, order: float, domain: str = "linear", factor: float = 1.0) -> Stage:
    return type(name.title(), (_Scale,), {"name": name, "order": order, "domain": domain})(factor)


def test_foveation_is_an_identity_stub_before_the_lens():
    image = torch.rand(3, 5, 4)
    gazing = RuntimeState(gaze=(0.3, -0.2))
    stage = Foveation()
    assert stage.is_identity(gazing) and stage.is_identity(RuntimeState(2.0, 0.5))
    assert foveation(image, (0.3, -0.2)) is image and stage(image, gazing) is image
    assert stage.name == "foveation" and stage.domain == "linear" and stage.order < LensPrewarp.order
    p = Pipeline.from_config({"foveation": True, "lens": True, "oled": False})
    assert p.names == ["foveation", "lens"] and p.active(gazing) == ["lens"]


def test_pipeline_orders_by_order_then_name_and_skips_identities():
    b, a, c = _stage("b", 1.0, factor=3.0), _stage("a", 1.0, factor=2.0), _stage("c", 0.5, factor=1.0)
    p = Pipeline([b, a, c]).double()
    assert p.names == ["c", "a", "b"]  # c first by order; a before b by name at equal order
    image = torch.tensor([0.2, 0.5, 0.9], dtype=torch.float64)[:, None, None].expand(3, 2, 2)
    _CALLS.clear()
    eye, rec = p.run_recorded(image)
    assert _CALLS == ["a", "b"] and rec["stages_run"] == ["a", "b"]  # c is the identity: not called
    assert torch.allclose(eye, linear_to_srgb(srgb_to_linear(image) * 6.0), atol=1e-12)
    # no physical stage: post and displayed are the eye image, rendered the input
    assert torch.equal(rec["post"], eye) and torch.equal(rec["displayed"], eye) and torch.equal(rec["rendered"], image)
    assert rec["diagnostics"] == {}
    assert p.active(RuntimeState()) == ["a", "b"]
    assert "a" in p and "z" not in p and p["b"] is b
    with pytest.raises(KeyError, match="no stage 'z'"):
        p["z"]


def test_pipeline_converts_domains_only_around_stages_that_run():
    lin, enc = _stage("lin", 1.0, "linear", 2.0), _stage("enc", 2.0, "srgb", 0.5)
    image = torch.rand(3, 3, 3, dtype=torch.float64)
    out = Pipeline([lin, enc]).double()(image)
    assert torch.allclose(out, linear_to_srgb(srgb_to_linear(image) * 2.0) * 0.5, atol=1e-12)
    only_srgb = Pipeline([_stage("lin", 1.0, "linear", 1.0), enc]).double()(image)
    assert torch.allclose(only_srgb, image * 0.5, atol=1e-15)  # skipped linear stage: no round trip


def test_pipeline_post_is_taken_before_the_first_physical_stage():
    p = Pipeline([_stage("pre", 1.0, factor=0.5), _stage("oled", 40.0, factor=2.0), _stage("optics", 50.0, factor=3.0)]).double()
    image = torch.rand(3, 2, 3, dtype=torch.float64)
    eye, rec = p.run_recorded(image)
    lin = srgb_to_linear(image)
    assert torch.allclose(rec["post"], linear_to_srgb(lin * 0.5), atol=1e-12)
    assert torch.allclose(rec["displayed"], linear_to_srgb(lin * 1.0), atol=1e-12)  # after oled, before optics
    assert torch.allclose(eye, linear_to_srgb(lin * 3.0), atol=1e-12)
    assert rec["stages_run"] == ["pre", "oled", "optics"]


def test_pipeline_refusals_name_what_is_wrong():
    nameless = _stage("x", 1.0)
    nameless.name = ""
    with pytest.raises(InputValueError, match=r"stages\[1\] \(X\) has no name"):
        Pipeline([_stage("a", 1.0), nameless])
    with pytest.raises(InputValueError, match="stage 'hsv' has domain 'hsv'"):
        Pipeline([_stage("hsv", 1.0, "hsv")])
    with pytest.raises(InputValueError, match="effects\\['resample'\\] is a stage named 'lens'"):
        Pipeline.from_config({"resample": LensPrewarp()})
    with pytest.raises(InputValueError, match="effects\\['resample'\\]"):
        Pipeline.from_config({"resample": {"no_such_option": 1}})
    with pytest.raises(ShapeError, match="larger than the native size"):
        Pipeline([_stage("a", 1.0)])(torch.rand(3, 4, 4), native_size=(4, 3))
    assert Pipeline.from_config({"resample": None, "display": False}).names == ["oled"]


# --- colour -------------------------------------------------------------------------------------

def test_convert_domain_identity_and_refusal():
    x = torch.rand(3, 2, 2, dtype=torch.float64)
    assert convert_domain(x, "linear", "linear") is x and convert_domain(x, "srgb", "srgb") is x
    assert torch.equal(convert_domain(x, "srgb", "linear"), srgb_to_linear(x))
    assert torch.equal(convert_domain(x, "linear", "srgb"), linear_to_srgb(x))
    with pytest.raises(ValueError, match="'srgb' -> 'xyz'"):
        convert_domain(x, "srgb", "xyz")  # type: ignore[arg-type]


# --- psf_fast edge cases ------------------------------------------------------------------------

@pytest.mark.parametrize("radiometry", ["radiance", "energy"])
def test_psf_fast_is_exact_for_any_zone_size_at_tol_zero_and_for_one_field_zones(radiometry):
    """A 4 x 4 field grid of different PSFs: zones of 1 (any tol), 3 (not dividing 4) and 10 (larger
    than the grid) at tol=0 all equal the brute-force splat."""
    bank = synthetic_bank(K=5, G=4, L=2, uniform=False, identity=False, seed=2)
    rb = bank.resample_to(12, 10, dtype=torch.float64, radiometry=radiometry)
    x = torch.rand(2, 12, 10, dtype=torch.float64, generator=torch.Generator().manual_seed(4))
    ref = psf_reference(x, rb)
    for zone, tol in ((1, 0.9), (3, 0.0), (10, 0.0), (4, 0.0)):
        assert torch.allclose(psf_fast(x, rb, tol=tol, zone=zone), ref, atol=1e-10, rtol=0), (zone, tol)


@pytest.mark.parametrize("radiometry", ["radiance", "energy"])
def test_psf_fast_extreme_tol_is_rank_one(radiometry):
    """tol near 1 keeps one eigen-PSF per group: the same operator as max_rank=1, and not exact."""
    bank = synthetic_bank(K=5, G=4, L=2, uniform=False, identity=False, seed=2)
    rb = bank.resample_to(12, 10, dtype=torch.float64, radiometry=radiometry)
    x = torch.rand(2, 12, 10, dtype=torch.float64, generator=torch.Generator().manual_seed(5))
    rank_one = psf_fast(x, rb, tol=0.999, zone=4)
    assert torch.allclose(rank_one, psf_fast(x, rb, tol=0.0, zone=4, max_rank=1), atol=1e-12, rtol=0)
    ref = psf_reference(x, rb)
    assert float((rank_one - ref).norm() / ref.norm()) > 1e-3


def test_psf_fast_refuses_bad_knobs():
    rb = synthetic_bank(K=3, G=2, L=1).resample_to(6, 6, dtype=torch.float64)
    x = torch.rand(1, 6, 6, dtype=torch.float64)
    for tol in (1.0, -0.01, float("nan"), "0.1"):
        with pytest.raises(InputValueError, match=r"tol must be in \[0, 1\)"):
            psf_fast(x, rb, tol=tol)  # type: ignore[arg-type]
    for zone in (0, -2, 2.0):
        with pytest.raises(InputValueError, match="zone must be an int >= 1"):
            psf_fast(x, rb, zone=zone)  # type: ignore[arg-type]
    with pytest.raises(InputValueError, match="primaries"):
        psf_fast(x.float(), rb)
    assert psf_fast(x, rb, tol=0.0, zone=1).shape == (1, 6, 6)


# --- distributed (CPU, one process) -------------------------------------------------------------

def test_init_distributed_refusals_name_the_argument(monkeypatch):
    from controlgs_adapter.distributed import init_distributed

    with pytest.raises(InputValueError, match="exchange must be one of .*'fast'"):
        init_distributed(exchange="fast")
    for timeout in (0.0, -1.0, float("nan")):
        with pytest.raises(InputValueError, match="timeout must be > 0 seconds"):
            init_distributed(timeout=timeout)
    env = {"RANK": "0", "WORLD_SIZE": "2", "LOCAL_RANK": "0", "MASTER_ADDR": "127.0.0.1", "MASTER_PORT": "1"}
    for k, v in env.items():
        monkeypatch.setenv(k, v)
    with pytest.raises(InputValueError, match="backend must be 'gloo' or 'nccl', got 'mpi'"):
        init_distributed("mpi")


def test_shard_scenes_refuses_an_empty_list_and_batch_equal_to_world_is_fine():
    from controlgs_adapter.distributed import DistContext, shard_scenes

    with pytest.raises(InputValueError, match="scenes must name at least one scene"):
        shard_scenes([], DistContext())
    DistContext(rank=2, world_size=3).check_batch(3)  # the bound: one view per rank
    with pytest.raises(InputValueError, match=r"need 0 <= rank < world_size, got rank=3, world_size=3"):
        DistContext(rank=3, world_size=3)


def test_an_existing_one_process_gloo_group_is_used_as_it_is():
    import torch.distributed as dist

    from controlgs_adapter.distributed import DistContext, init_distributed

    if not dist.is_available() or dist.is_initialized():
        pytest.skip("torch.distributed unavailable or a group already exists in this process")
    dist.init_process_group("gloo", store=dist.HashStore(), rank=0, world_size=1)
    try:
        ctx = init_distributed(exchange="dense")
        assert (ctx.rank, ctx.world_size, ctx.backend, ctx.device, ctx.exchange) == (0, 1, "gloo", torch.device("cpu"), "dense")
        assert isinstance(ctx, DistContext) and ctx.is_main and not ctx.is_distributed
        p = torch.nn.Parameter(torch.zeros(2, 3))
        p.grad = torch.arange(6.0).reshape(2, 3)
        assert ctx.sync_gradients([p], row_sparse=[p], loss=1.5, step=4) == 1.5
        assert torch.equal(p.grad, torch.arange(6.0).reshape(2, 3))  # one rank: the sum is its own gradient
        ctx.close()  # not its group: left for its owner
        assert dist.is_initialized()
    finally:
        dist.destroy_process_group()


# --- DisplayLUTMap, BankMap, LensPrewarp refusals -----------------------------------------------

def _display_tables(hd: int = 5, wd: int = 4) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """A display table whose displacement is ``M_c q + t_c`` at display point ``q`` (exact under
    bilinear interpolation) and gain ``1 + 0.1 c``: ``(displacement, gain, M)``."""
    m = torch.tensor([[0.10, -0.05], [0.02, 0.08], [-0.06, 0.04]], dtype=torch.float64)  # diagonal of M_c
    t = torch.tensor([[0.01, 0.02], [-0.03, 0.0], [0.0, -0.01]], dtype=torch.float64)
    q = pixel_grid((hd, wd), torch.float64)
    disp = m[:, None, None, :] * q + t[:, None, None, :]
    gain = (1.0 + 0.1 * torch.arange(3, dtype=torch.float64))[:, None, None].expand(3, hd, wd).clone()
    return disp, gain, torch.cat([m, t], 1)


@pytest.mark.parametrize("placement, size, half", [("stretch", (4, 8), (1.0, 1.0)), ("fit", (4, 8), (1.0, 0.5)),
                                                  ("fit", (6, 3), (0.5, 1.0))])
def test_display_lut_map_samples_the_image_region_of_the_display(placement, size, half):
    """grid(u) = (u h + disp(u h)) / h on a square display: a 4 x 8 image fit on it spans the full
    width and half the height (h = (1, 0.5))."""
    disp, gain, mt = _display_tables()
    lut = DisplayLUTMap({"exact": (disp, gain)}, display_mm=(24.0, 24.0), placement=placement)
    grid, got_gain = lut(size, torch.float64, CPU)
    h = torch.tensor(half, dtype=torch.float64)
    q = pixel_grid(size, torch.float64) * h  # display-normalised
    want = (q + mt[:, None, None, :2] * q + mt[:, None, None, 2:]) / h
    assert torch.allclose(grid, want, atol=1e-6, rtol=0)  # tables are stored as float32
    assert torch.allclose(got_gain, gain[:, :1, :1].expand(3, *size), atol=1e-6)
    assert not lut.is_identity()


def test_display_lut_map_table_choice():
    disp, gain, _ = _display_tables()
    other = (disp * 2.0, gain)
    assert DisplayLUTMap({"distortion": (disp, gain), "exact": other}).table_mode() == "distortion"  # first
    assert DisplayLUTMap({"distortion": (disp, gain), "exact": other}, mode="exact").table_mode() == "exact"

    class _Optics(torch.nn.Module):
        mode = "fast"

    optics = _Optics()
    assert DisplayLUTMap({"distortion": (disp, gain), "exact": other}).follow(optics).table_mode() == "exact"
    only_distortion = DisplayLUTMap({"distortion": (disp, gain)}).follow(optics)
    with pytest.raises(InputValueError, match=r"tables for \('distortion',\), not for optics mode 'fast'"):
        only_distortion.table_mode()
    fast = DisplayLUTMap({"fast": (disp, gain), "exact": other}, mode="fast")
    assert fast.table_mode() == "fast"  # its own fast table wins over the exact one


def test_display_lut_map_refusals(tmp_path):
    from controlgs_adapter.errors import FileFormatError
    from controlgs_adapter.formats.safetensors import save_tensors

    disp, gain, _ = _display_tables()
    with pytest.raises(InputValueError, match="tables must hold at least one optics mode"):
        DisplayLUTMap({})
    with pytest.raises(InputValueError, match="placement must be one of .*'centre'"):
        DisplayLUTMap({"exact": (disp, gain)}, placement="centre")  # type: ignore[arg-type]
    with pytest.raises(InputValueError, match="table modes must be among .*'paraxial'"):
        DisplayLUTMap({"paraxial": (disp, gain)})
    with pytest.raises(ShapeError, match="table 'exact' needs at least 2x2 samples"):
        DisplayLUTMap({"exact": (disp[:, :1], gain[:, :1])})
    with pytest.raises(ShapeError, match=r"gain\['exact'\]"):
        DisplayLUTMap({"exact": (disp, gain[:, :2])})
    kind = {"kind": "controlgs-prewarp-display-lut", "format_version": 1}
    no_modes = save_tensors(tmp_path / "no_modes.safetensors", {"gain_exact": gain.float()}, {}, **kind)
    with pytest.raises(FileFormatError, match="no_modes.safetensors: display LUT header lacks its modes"):
        DisplayLUTMap.load(no_modes)
    lacking = save_tensors(tmp_path / "lacking.safetensors", {"gain_exact": gain.float()}, {"modes": ["exact"]}, **kind)
    with pytest.raises(FileFormatError, match=r"lacking.safetensors: display LUT lacks \['displacement_exact'\]"):
        DisplayLUTMap.load(lacking)
    bad = save_tensors(tmp_path / "bad.safetensors", {"displacement_exact": disp[:, :1].float(), "gain_exact": gain[:, :1].float()},
                       {"modes": ["exact"]}, **kind)
    with pytest.raises(FileFormatError, match="bad.safetensors: table 'exact' needs at least 2x2"):
        DisplayLUTMap.load(bad)
    saved = DisplayLUTMap({"exact": (disp, gain)}, display_mm=(20.0, 10.0), meta={"bank": "x"}).save(tmp_path / "ok.safetensors")
    back = DisplayLUTMap.load(saved, placement="stretch")
    assert back.display_mm == (20.0, 10.0) and back.placement == "stretch" and back.meta == {"bank": "x"}
    assert torch.equal(back.displacement_exact, disp.float())


def test_lens_prewarp_and_bank_map_refusals(tmp_path):
    from controlgs_adapter.downstream.lens import BankMap, lens_prewarp
    from controlgs_adapter.downstream.optics.bank import PSFBank
    from controlgs_adapter.errors import FileFormatError
    from controlgs_adapter.formats.safetensors import save_tensors

    img = torch.rand(3, 4, 4)
    with pytest.raises(InputValueError, match="basis must be one of .*'xyz'"):
        lens_prewarp(img, pixel_grid((4, 4)).expand(3, -1, -1, -1).contiguous(), basis="xyz")  # type: ignore[arg-type]
    with pytest.raises(InputValueError, match="basis must be one of .*'xyz'"):
        LensPrewarp(basis="xyz")  # type: ignore[arg-type]
    with pytest.raises(InputValueError, match="either prewarp_map or coefficients, not both"):
        LensPrewarp(MLPMap(), coefficients=[[0.1]] * 3)
    two = synthetic_bank(L=2)
    with pytest.raises(InputValueError, match="bank must have 3 wavelengths .*600.0, 500.0"):
        BankMap(two)
    with pytest.raises(InputValueError, match="bank must have 3 wavelengths"):
        LensPrewarp.from_psf_bank(two, (4, 4))
    bank = PSFBank.default()
    with pytest.raises(InputValueError, match="placement must be one of .*'centre'"):
        BankMap(bank, "centre")  # type: ignore[arg-type]
    with pytest.raises(InputValueError, match="gain must be 'jacobian' or None, got 'area'"):
        BankMap(bank, gain="area")  # type: ignore[arg-type]
    with pytest.raises(InputValueError, match="a gain tensor needs a LUT size"):
        LensPrewarp.from_psf_bank(bank, gain=torch.ones(3, 4, 4))
    with pytest.raises(InputValueError, match="optics must be an optics stage with a PSFBank .*Identity"):
        LensPrewarp.for_optics(torch.nn.Identity())

    class _Optics(torch.nn.Module):
        def __init__(self, placement: str = "fit") -> None:
            super().__init__()
            self.bank, self.placement = bank, placement

    with pytest.raises(InputValueError, match="source must be 'fitted' or 'chief_rays', got 'traced'"):
        LensPrewarp.for_optics(_Optics(), source="traced")  # type: ignore[arg-type]
    with pytest.raises(InputValueError, match="gain applies to source='chief_rays'"):
        LensPrewarp.for_optics(_Optics(), gain="jacobian")
    with pytest.raises(InputValueError, match="optics.placement must be one of .*'crop'"):
        LensPrewarp.for_optics(_Optics("crop"), source="chief_rays")
    chief = LensPrewarp.for_optics(_Optics("stretch"), source="chief_rays", gain="jacobian", basis="rgb")
    assert isinstance(chief.map, BankMap) and (chief.map.placement, chief.map.gain, chief.basis) == ("stretch", "jacobian", "rgb")
    no_gain = save_tensors(tmp_path / "lut.safetensors", {"grid": torch.zeros(3, 2, 2, 2)}, {},
                           kind="controlgs-prewarp-lut", format_version=1)
    with pytest.raises(FileFormatError, match=r"lut.safetensors: pre-warp LUT lacks \['gain'\]"):
        LensPrewarp.load_lut(no_gain)


# --- RadialMap, lens_prewarp in the primaries basis ---------------------------------------------

def test_radial_map_default_and_higher_orders_by_hand():
    from controlgs_adapter.downstream.lens import CARDBOARD_RADIAL, RadialMap

    landing = (606.5, 611.8, 617.1)  # px from the centre of a 1024 px display, corner (r^2 = 2)
    assert torch.allclose(RadialMap().coefficients, torch.tensor([[(d / 512 - 1) / 2] for d in landing]))
    assert RadialMap().coefficients.tolist() == RadialMap(CARDBOARD_RADIAL).coefficients.tolist()
    k = [[0.1, 0.02], [0.0, -0.03], [-0.05, 0.0]]
    m = RadialMap(k)
    grid, gain = m((4, 4), torch.float64, CPU)  # square image on the square display: r = |p|
    assert gain is None
    p = pixel_grid((4, 4), torch.float64)
    r2 = (p ** 2).sum(-1)
    for c, (k1, k2) in enumerate(k):
        want = p * (1 + k1 * r2 + k2 * r2 ** 2)[..., None]
        assert torch.allclose(grid[c], want, atol=1e-7, rtol=0)  # coefficients are stored as float32
    with torch.no_grad():
        m.coefficients[1, 1] = 0.0  # in place: the cached grid must follow
    assert torch.allclose(m((4, 4), torch.float64, CPU)[0][1], p, atol=1e-12)
    assert not m.is_identity() and RadialMap([[0.0, 0.0]] * 3).is_identity()


def test_learnable_radial_lens_is_skipped_only_outside_training():
    stage = LensPrewarp.radial([[0.0]] * 3, learnable=True)
    assert not stage.train().is_identity(RuntimeState())  # trainable: runs so that it gets gradients
    assert stage.eval().is_identity(RuntimeState())
    stage.map.coefficients.requires_grad_(False)
    assert stage.train().is_identity(RuntimeState())


def test_lens_prewarp_in_the_primaries_basis_shifts_each_primary():
    """Whole-pixel shifts, a different one per channel: in the primaries basis each display primary
    is shifted (zero fill) and the result converted back to RGB; brute force by slicing."""
    from controlgs_adapter.downstream.color import primaries_to_rgb, rgb_to_primaries
    from controlgs_adapter.downstream.lens import lens_prewarp

    h, w = 5, 6
    img = torch.rand(2, 3, h, w, dtype=torch.float64, generator=torch.Generator().manual_seed(7))
    shifts = [(1, 0), (0, -2), (-1, 1)]  # (dy, dx) pixels sampled from: out[y, x] = in[y + dy, x + dx]
    base = pixel_grid((h, w), torch.float64)
    grid = torch.stack([base + torch.tensor([2.0 * dx / w, 2.0 * dy / h], dtype=torch.float64) for dy, dx in shifts])
    gain = torch.tensor([1.0, 0.5, 2.0], dtype=torch.float64)[:, None, None].expand(3, h, w).contiguous()

    def shifted(x: torch.Tensor) -> torch.Tensor:
        out = torch.zeros_like(x)
        for c, (dy, dx) in enumerate(shifts):
            src = torch.nn.functional.pad(x[:, c], (2, 2, 2, 2))
            out[:, c] = src[:, 2 + dy:2 + dy + h, 2 + dx:2 + dx + w] * gain[c, 0, 0]
        return out

    assert torch.allclose(lens_prewarp(img, grid, gain, basis="rgb"), shifted(img), atol=1e-12)
    want = primaries_to_rgb(shifted(rgb_to_primaries(img)))
    assert torch.allclose(lens_prewarp(img, grid, gain, basis="primaries"), want, atol=1e-12)
    assert not torch.allclose(want, shifted(img), atol=1e-3)


def test_primaries_matrix_from_the_iec_srgb_matrix_by_hand():
    """C^-1 M with M the IEC 61966-2-1 sRGB -> XYZ matrix as printed (4 digits) and C the CIE 1931
    2-degree CMFs at 656 / 550 / 486 nm; rows scaled so that white drives every primary at 1."""
    colour = pytest.importorskip("colour")
    import numpy as np

    from controlgs_adapter.downstream.color import primaries_to_rgb_matrix, rgb_to_primaries_matrix

    iec = np.array([[0.4124, 0.3576, 0.1805], [0.2126, 0.7152, 0.0722], [0.0193, 0.1192, 0.9505]])
    cmfs = colour.MSDS_CMFS["CIE 1931 2 Degree Standard Observer"]
    c = np.stack([np.asarray(cmfs[w], dtype=np.float64) for w in (656, 550, 486)], axis=1)
    raw = np.linalg.solve(c, iec)
    want = raw / raw.sum(1, keepdims=True)
    got = rgb_to_primaries_matrix().numpy()
    assert np.allclose(got, want, atol=2e-3)
    assert np.allclose(got.sum(1), 1.0, atol=1e-12)
    assert np.allclose(primaries_to_rgb_matrix().numpy(), np.linalg.inv(want), atol=5e-3)
    assert rgb_to_primaries_matrix(torch.float32).dtype == torch.float32


def test_for_optics_checks_a_fitted_lut_and_falls_back_to_chief_rays(tmp_path):
    from controlgs_adapter.downstream.lens import BankMap
    from controlgs_adapter.downstream.optics.bank import PSFBank

    bank = PSFBank.default()

    class _Optics(torch.nn.Module):
        def __init__(self, bank_: PSFBank, radiometry: str, mode: str = "exact") -> None:
            super().__init__()
            self.bank, self.radiometry, self.mode, self.placement = bank_, radiometry, mode, "fit"

    disp, gain, _ = _display_tables()
    fp = bank_fingerprint(bank)
    lut = DisplayLUTMap({"distortion": (disp, gain), "exact": (disp * 2, gain)},
                        meta={"bank": fp, "radiometry": "energy"}).save(tmp_path / "fit.safetensors")
    with pytest.raises(InputValueError, match="fit.safetensors: this pre-warp LUT was fitted for radiometry 'energy'"):
        LensPrewarp.for_optics(_Optics(bank, "radiance"), lut=lut)
    optics = _Optics(bank, "energy", mode="distortion")
    stage = LensPrewarp.for_optics(optics, lut=lut)
    assert isinstance(stage.map, DisplayLUTMap) and stage.map.table_mode() == "distortion"
    optics.mode = "fast"
    assert stage.map.table_mode() == "exact"  # follows the optics' current mode
    other = copy.copy(bank)
    other._cache, other.chief = {}, bank.chief * 1.001  # own cache: the default bank is process-wide
    with pytest.raises(InputValueError, match=f"another PSF bank .*{fp}"):
        LensPrewarp.for_optics(_Optics(other, "energy"), lut=lut)
    for radiometry, fallback in (("energy", "jacobian"), ("radiance", None)):
        with pytest.warns(UserWarning, match=f"no fitted pre-warp LUT for this PSF bank and radiometry '{radiometry}'"):
            chief = LensPrewarp.for_optics(_Optics(other, radiometry))
        assert isinstance(chief.map, BankMap) and chief.map.gain == fallback and chief.map.bank is other


def test_lut_map_evaluation_follows_in_place_edits():
    grid = pixel_grid((3, 3), torch.float64).expand(3, -1, -1, -1).clone()
    m = LUTMap(grid)
    first, _ = m((5, 5), torch.float64, CPU)
    assert torch.allclose(first, pixel_grid((5, 5), torch.float64).expand(3, -1, -1, -1), atol=1e-7)
    m.displacement[:, :, :, 0] += 0.25  # a uniform shift in x
    moved, _ = m((5, 5), torch.float64, CPU)
    assert torch.allclose(moved[..., 0] - first[..., 0], torch.full((3, 5, 5), 0.25, dtype=torch.float64), atol=1e-7)
