"""Tests of ``controlgs_adapter.rendering.rasterizers``: the rasterizer registry and how one is chosen (argument,
context, environment, auto), the torch splatter's and gsplat's availability, and the gsplat adaptor's
conventions (against a stand-in module that renders with the project splatter, and on a GPU with gsplat)."""

from __future__ import annotations

import types
from typing import Any

import pytest
from helpers.splat_scenes import gaussian_cloud
import torch

from controlgs_adapter.errors import InputValueError
from controlgs_adapter.rendering import rasterizers
from controlgs_adapter.rendering.rasterizers import (
    RASTERIZER_ENV,
    GsplatRasterizer,
    Rasterizer,
    TorchSplatter,
    gsplat_alpha_max,
    rasterize_gaussians,
    select_rasterizer,
    use_rasterizer,
)
from controlgs_adapter.rendering.splatter import ALPHA_MAX, LOW_PASS, NEAR_PLANE, rasterize
from controlgs_adapter.state import Camera

CPU, CUDA = torch.device("cpu"), torch.device("cuda")


def _two_gaussians(dtype: torch.dtype = torch.float32) -> tuple[list[torch.Tensor], Camera]:
    """Two Gaussians in front of an 8 x 6 camera."""
    k = torch.tensor([[8.0, 0.0, 4.0], [0.0, 8.0, 3.0], [0.0, 0.0, 1.0]])
    cam = Camera(torch.eye(4), k, 8, 6)
    g = [torch.tensor([[0.0, 0.0, 2.0], [0.1, 0.0, 3.0]]), torch.full((2, 3), 0.2), torch.tensor([[1.0, 0, 0, 0]] * 2),
         torch.tensor([0.7, 0.9]), torch.tensor([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])]
    return [t.to(dtype) for t in g], cam


def _fake_gsplat(version: str, seen: dict):
    """A stand-in for the gsplat module whose ``rasterization`` renders with the project splatter,
    checking the arguments the plug-in passes (gsplat's documented signature and shapes)."""

    def rasterization(means, quats, scales, opacities, colors, viewmats, Ks, width, height, *, near_plane, eps2d,
                      packed, render_mode, backgrounds, rasterize_mode):
        assert viewmats.shape == (1, 4, 4) and Ks.shape == (1, 3, 3) and render_mode == "RGB+D" and not packed
        assert (near_plane, eps2d, rasterize_mode) == (NEAR_PLANE, LOW_PASS, "classic")
        assert backgrounds is None or backgrounds.shape == (1, 3)
        seen["opacities"] = opacities
        out = rasterize(means, scales, quats, opacities, colors, Camera(viewmats[0], Ks[0], width, height),
                        None if backgrounds is None else backgrounds[0])
        rgbd = torch.cat([out.color, out.depth]).permute(1, 2, 0).unsqueeze(0)  # [1, H, W, 4]
        radii = out.visible.to(torch.int32)[None, :, None].expand(1, -1, 2)  # [1, N, 2]
        return rgbd, out.alpha.permute(1, 2, 0).unsqueeze(0), {"radii": radii}

    return types.SimpleNamespace(__version__=version, rasterization=rasterization)


def _gsplat_on_gpu() -> str | None:
    if not torch.cuda.is_available():
        return "no GPU available in this run: gsplat vs project splatter agreement not run"
    mod = rasterizers._import_gsplat()
    return mod if isinstance(mod, str) else None


# ----------------------------------------------------------------------------- choosing a rasterizer

def test_env_name_and_base_class() -> None:
    assert RASTERIZER_ENV == "CONTROLGS_RASTERIZER"
    assert repr(TorchSplatter()) == "TorchSplatter(name='torch')" and GsplatRasterizer.name == "gsplat"
    base = Rasterizer()
    with pytest.raises(NotImplementedError):
        base.unavailable(CPU, torch.float32)
    with pytest.raises(NotImplementedError):
        base(*_two_gaussians()[0], _two_gaussians()[1])


def test_gsplat_is_chosen_only_on_cuda_when_it_imports(monkeypatch):
    monkeypatch.delenv(rasterizers.RASTERIZER_ENV, raising=False)
    monkeypatch.setattr(rasterizers, "_import_gsplat", lambda: _fake_gsplat("1.5.3", {}))
    assert select_rasterizer("cpu").name == "torch"
    assert select_rasterizer(CUDA).name == "gsplat"  # a device object needs no GPU
    assert select_rasterizer(CUDA, torch.float64).name == "torch"  # gsplat is float32 only
    with use_rasterizer("torch"):
        assert select_rasterizer(CUDA).name == "torch"
    monkeypatch.setenv(rasterizers.RASTERIZER_ENV, "torch")
    assert select_rasterizer(CUDA).name == "torch"
    monkeypatch.delenv(rasterizers.RASTERIZER_ENV)
    monkeypatch.setattr(rasterizers, "_import_gsplat", lambda: "gsplat does not import (ImportError: no module)")
    assert select_rasterizer(CUDA).name == "torch"
    with pytest.raises(InputValueError, match="'gsplat' cannot render .*does not import"):
        select_rasterizer(CUDA, rasterizer="gsplat")
    with pytest.raises(InputValueError, match="CUDA devices only"):
        select_rasterizer("cpu", rasterizer="gsplat")
    with pytest.raises(InputValueError, match=r"not registered; registered: \['gsplat', 'torch'\]"):
        select_rasterizer("cpu", rasterizer="nvdiffrast")


def test_selection_precedence(monkeypatch: pytest.MonkeyPatch) -> None:
    class Mine(Rasterizer):
        name = "mine"

        def unavailable(self, device: Any, dtype: Any) -> str | None:
            return None if dtype == torch.float64 else "float64 only"

    mine = Mine()
    monkeypatch.setenv(RASTERIZER_ENV, "nope")
    with pytest.raises(InputValueError, match=r"rasterizer 'nope' is not registered; registered: \['gsplat', 'torch'\] "
                                              r"\(or 'auto'\)"):
        select_rasterizer(CPU)
    with use_rasterizer("torch"):  # the context beats the environment
        assert select_rasterizer(CPU).name == "torch"
        assert select_rasterizer(CPU, torch.float64, mine) is mine  # the argument beats both
        with use_rasterizer(mine):
            assert select_rasterizer(CPU, torch.float64) is mine
            with pytest.raises(InputValueError, match="rasterizer 'mine' cannot render torch.float32 on cpu: float64 only"):
                select_rasterizer(CPU, torch.float32)
        assert select_rasterizer(CPU).name == "torch"  # the inner block's choice is reset
        with use_rasterizer(None):  # None: back to the environment
            with pytest.raises(InputValueError, match="'nope' is not registered"):
                select_rasterizer(CPU)
    with pytest.raises(InputValueError, match="'nope' is not registered"):  # the outer choice is reset too
        select_rasterizer(CPU)
    monkeypatch.setenv(RASTERIZER_ENV, "")
    assert select_rasterizer(CPU).name == "torch"  # empty: auto
    monkeypatch.setenv(RASTERIZER_ENV, "auto")
    assert select_rasterizer("cpu", torch.float64).name == "torch"


def test_auto_refusal_lists_every_reason(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.delenv(RASTERIZER_ENV, raising=False)
    monkeypatch.setattr(rasterizers, "_import_gsplat", lambda: types.SimpleNamespace())
    with pytest.raises(InputValueError) as e:
        select_rasterizer(CPU, torch.float16)
    assert str(e.value) == ("no registered rasterizer can render torch.float16 on cpu: gsplat: runs on CUDA devices "
                            "only, not cpu; torch: needs float32 or float64, got torch.float16")
    with pytest.raises(InputValueError, match="'torch' cannot render torch.float16"):
        select_rasterizer(CPU, torch.float16, "torch")


def test_rasterize_gaussians_passes_everything_on() -> None:
    g, cam = _two_gaussians(torch.float64)
    bg = torch.tensor([0.0, 0.5, 1.0], dtype=torch.float64)
    out = rasterize_gaussians(*g, cam, bg, rasterizer="torch")
    want = rasterize(*g, cam, bg)
    assert out.color.dtype == torch.float64 and torch.equal(out.color, want.color) and torch.equal(out.depth, want.depth)
    seen: list[tuple[Any, ...]] = []

    class Spy(Rasterizer):
        name = "spy"

        def unavailable(self, device: Any, dtype: Any) -> str | None:
            seen.append((device, dtype))
            return None

        def __call__(self, *args: Any) -> Any:
            seen.append(args)
            return "out"

    assert rasterize_gaussians(*g, cam, bg, rasterizer=Spy()) == "out"
    assert seen[0] == (CPU, torch.float64)  # chosen for means' device and dtype
    assert seen[1][5] is cam and seen[1][6] is bg and seen[1][0] is g[0] and seen[1][2] is g[2]


# ----------------------------------------------------------------------------- availability

def test_torch_splatter_dtypes() -> None:
    t = TorchSplatter()
    assert t.unavailable(CPU, torch.float32) is None and t.unavailable(CPU, torch.float64) is None
    assert t.unavailable(CUDA, torch.float32) is None  # any device
    assert t.unavailable(CPU, torch.float16) == "needs float32 or float64, got torch.float16"
    assert t.unavailable(CPU, torch.bfloat16) == "needs float32 or float64, got torch.bfloat16"


def test_gsplat_unavailable_reasons(monkeypatch: pytest.MonkeyPatch) -> None:
    g = GsplatRasterizer()
    monkeypatch.setattr(rasterizers, "_import_gsplat", lambda: types.SimpleNamespace())
    assert g.unavailable(CPU, torch.float32) == "runs on CUDA devices only, not cpu"
    assert g.unavailable("cpu", torch.float32) == "runs on CUDA devices only, not cpu"  # a device name works too
    assert g.unavailable(CUDA, torch.float64) == "needs float32, got torch.float64"
    assert g.unavailable(CUDA, torch.float32) is None
    monkeypatch.setattr(rasterizers, "_import_gsplat", lambda: "gsplat does not import (x)")
    assert g.unavailable(CUDA, torch.float32) == "gsplat does not import (x)"
    with pytest.raises(InputValueError, match=r"rasterizer 'gsplat': gsplat does not import \(x\)"):
        g(*_two_gaussians()[0], _two_gaussians()[1])


def test_import_gsplat_reports_a_broken_install(monkeypatch: pytest.MonkeyPatch) -> None:
    def boom(name: str) -> Any:
        raise OSError("libcudart.so: cannot open")

    rasterizers._import_gsplat.cache_clear()
    monkeypatch.setattr(rasterizers.importlib, "import_module", boom)
    try:
        assert rasterizers._import_gsplat() == ("gsplat does not import (OSError: libcudart.so: cannot open); install it "
                                                "with 'pip install --no-deps gsplat'")
    finally:
        rasterizers._import_gsplat.cache_clear()


def test_gsplat_alpha_clamp_by_version() -> None:
    """gsplat releases before 1.6 clamp alpha at 0.999, later ones at 0.99; the version is compared as numbers."""
    assert gsplat_alpha_max("1.5.3") == 0.999 and gsplat_alpha_max("1.4.0") == 0.999
    assert gsplat_alpha_max("1.6.0") == 0.99 and gsplat_alpha_max("2.0.1") == 0.99
    assert gsplat_alpha_max("1.10.0") == 0.99  # minor 10 > 6 (a string comparison would say otherwise)
    assert gsplat_alpha_max("1.6") == 0.99 and gsplat_alpha_max("1.5.99") == 0.999
    assert gsplat_alpha_max("0.9.0") == 0.999 and gsplat_alpha_max("2.0") == 0.99
    assert gsplat_alpha_max("0") == 0.999 and gsplat_alpha_max("dev") == 0.999  # unparsable: the old clamp


# ----------------------------------------------------------------------------- the gsplat adaptor

@pytest.mark.parametrize("version", ["1.5.3", "1.6.0"])
def test_gsplat_adaptor_conventions_on_cpu(monkeypatch, version):
    """The plug-in's marshalling (shapes, background, depth channel, visibility, the straight-through
    opacity cap for 0.999-clamping releases) against a stand-in that renders with the project splatter."""
    seen: dict = {}
    monkeypatch.setattr(rasterizers, "_import_gsplat", lambda: _fake_gsplat(version, seen))
    (means, scales, rotations, opacities, colors), cam = gaussian_cloud()
    opacities[::4] = 0.999  # opaque splats: above the project's 0.99 clamp
    opacities.requires_grad_(True)
    bg = torch.tensor([0.2, 0.3, 0.4])
    got = GsplatRasterizer()(means, scales, rotations, opacities, colors, cam, bg)
    capped = bool((opacities > ALPHA_MAX).any())
    assert capped  # the scene has splats above the cap
    if version == "1.5.3":
        assert float(seen["opacities"].detach().max()) <= float(torch.tensor(ALPHA_MAX)) + 1e-7
        want = rasterize(means, scales, rotations, opacities.detach().clamp(max=ALPHA_MAX), colors, cam, bg)
    else:
        assert torch.equal(seen["opacities"], opacities)
        want = rasterize(means, scales, rotations, opacities.detach(), colors, cam, bg)
    assert torch.equal(got.visible, want.visible)
    for k in ("color", "alpha", "depth"):  # the straight-through cap rounds like the clamp to ~1 ulp
        torch.testing.assert_close(getattr(got, k), getattr(want, k), rtol=0, atol=1e-5, msg=k)
    assert got.color.shape == (3, 32, 48) and got.alpha.shape == got.depth.shape == (1, 32, 48)
    got.color.sum().backward()
    assert opacities.grad is not None and bool(opacities.grad.abs().sum() > 0)  # straight through the cap
    empty = GsplatRasterizer()(means[:0], scales[:0], rotations[:0], opacities[:0], colors[:0], cam, bg)
    assert torch.equal(empty.color, bg.view(3, 1, 1).expand(3, 32, 48)) and empty.visible.shape == (0,)


def test_gsplat_opacity_cap_passes_the_gradient_straight_through(monkeypatch):
    """With a 0.999-clamping gsplat (< 1.6) the adaptor caps opacities at 0.99 straight-through: a splat
    above the cap gets the gradient the splatter gives at the capped value (not zero, as a plain clamp would)."""
    monkeypatch.setattr(rasterizers, "_import_gsplat", lambda: _fake_gsplat("1.5.3", {}))
    (means, scales, rotations, opacities, colors), cam = gaussian_cloud(seed=3)
    opacities[::3] = 0.9995
    opacities.requires_grad_(True)
    GsplatRasterizer()(means, scales, rotations, opacities, colors, cam).color.sum().backward()
    capped = opacities.detach().clamp(max=ALPHA_MAX).requires_grad_(True)
    rasterize(means, scales, rotations, capped, colors, cam).color.sum().backward()
    above = opacities.detach() > ALPHA_MAX
    assert bool(above.any()) and bool((capped.grad[above] != 0).any())
    torch.testing.assert_close(opacities.grad, capped.grad, rtol=1e-5, atol=1e-6)


@pytest.mark.parametrize("with_background", [True, False])
def test_gsplat_empty_render_is_the_background_and_stays_in_the_graph(monkeypatch, with_background):
    """A view with no Gaussians (all culled by the decoder) renders the background (a copy of it) or black
    without calling gsplat (the stand-in has no ``rasterization``); its loss must back-propagate (zero gradients
    of the empty inputs), as with the torch splatter, not raise "element 0 of tensors does not require grad" at
    ``loss.backward()`` in a CUDA training step."""
    monkeypatch.setattr(rasterizers, "_import_gsplat", lambda: types.SimpleNamespace(__version__="1.6.0"))
    (means, scales, rotations, opacities, colors), cam = gaussian_cloud()
    bg = torch.tensor([0.2, 0.3, 0.4]) if with_background else None
    for r in (TorchSplatter(), GsplatRasterizer()):
        xs = [t[:0].clone().requires_grad_(True) for t in (means, scales, rotations, opacities, colors)]
        out = r(*xs, cam, bg)
        want = torch.zeros(3, 32, 48) if bg is None else bg.view(3, 1, 1).expand(3, 32, 48)
        assert torch.equal(out.color, want) and torch.equal(out.alpha, torch.zeros(1, 32, 48)), r.name
        assert out.color.requires_grad and out.alpha.requires_grad, r.name
        ((out.color - 1).square().sum() + out.alpha.sum()).backward()
        assert [tuple(x.grad.shape) for x in xs] == [(0, 3), (0, 3), (0, 4), (0,), (0, 3)], r.name
        assert out.depth.shape == (1, 32, 48) and float(out.depth.detach().abs().max()) == 0.0 and out.visible.dtype == torch.bool
        if bg is not None:
            out.color.detach()[0, 0, 0] = 5.0  # a copy, not a view of the background
            assert float(bg[0]) == pytest.approx(0.2)


@pytest.mark.skipif(_gsplat_on_gpu() is not None, reason=str(_gsplat_on_gpu()))
def test_gsplat_agrees_with_the_project_splatter_on_cuda():
    """Images and gradients within the documented convention differences (docs/reference/rasterizers.md): the
    footprint ring between 3 and 3.33 sigma holds splats of alpha <= o e^-4.5 < 0.0111."""
    leaves, cam = gaussian_cloud(n=400, device="cuda", max_opacity=0.95)
    bg = torch.tensor([0.1, 0.2, 0.3], device="cuda")
    grads = []
    for r in (TorchSplatter(), GsplatRasterizer()):
        xs = [t.clone().requires_grad_(True) for t in leaves]
        out = r(*xs, cam, bg)
        (out.color * torch.linspace(0, 1, out.color.numel(), device="cuda").view_as(out.color)).sum().backward()
        grads.append((out, [x.grad for x in xs]))
    (a, ga), (b, gb) = grads
    diff = (a.color - b.color).abs()
    assert float(diff.mean()) < 2e-3 and float(diff.max()) < 0.05
    assert float((a.alpha - b.alpha).abs().mean()) < 2e-3
    for name, x, y in zip(("means", "scales", "rotations", "opacities", "colors"), ga, gb):
        cos = torch.nn.functional.cosine_similarity(x.flatten(), y.flatten(), dim=0)
        assert float(cos) > 0.99, name
