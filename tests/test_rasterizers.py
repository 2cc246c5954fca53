"""Rasterizer plug-ins: registration, the automatic choice (gsplat only on CUDA when it imports),
the gsplat adaptor's argument conventions (checked on CPU against a stand-in module), and on a
GPU the agreement of gsplat with the project splatter."""

import types

import pytest
import torch

from controlgs_adapter import plugins
from controlgs_adapter.rendering import rasterizers
from controlgs_adapter.rendering.splatter import ALPHA_MAX, LOW_PASS, NEAR_PLANE, rasterize
from controlgs_adapter.errors import InputValueError
from controlgs_adapter.hookspecs import hookimpl
from controlgs_adapter.rendering.rasterizers import (GsplatRasterizer, Rasterizer, TorchSplatter, gsplat_alpha_max,
                                           rasterize_gaussians, select_rasterizer, use_rasterizer)
from controlgs_adapter.state import Camera

CUDA = torch.device("cuda")


def _scene(n: int = 40, seed: int = 0, device: str = "cpu", max_opacity: float = 0.9):
    g = torch.Generator().manual_seed(seed)
    means = torch.rand(n, 3, generator=g) * 2 - 1
    scales = torch.rand(n, 3, generator=g) * 0.15 + 0.02
    rotations = torch.randn(n, 4, generator=g)
    opacities = torch.rand(n, generator=g) * max_opacity
    colors = torch.rand(n, 3, generator=g)
    w2c = torch.eye(4)
    w2c[2, 3] = 3.0
    cam = Camera(w2c, torch.tensor([[40.0, 0, 24], [0, 40.0, 16], [0, 0, 1]]), 48, 32)
    return [t.to(device) for t in (means, scales, rotations, opacities, colors)], cam


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


def test_registered_through_the_hook_and_listed():
    names = list(plugins.rasterizers())
    assert names == ["gsplat", "torch"]  # the automatic choice tries gsplat first, torch always works
    assert {(i.kind, i.name) for i in plugins.plugin_report() if i.kind == "rasterizer"} == {
        ("rasterizer", "gsplat"), ("rasterizer", "torch")}
    assert all(i.source == plugins.BUILTIN_DIST for i in plugins.rasterizers().values())


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


def test_gsplat_alpha_clamp_by_version():
    assert gsplat_alpha_max("1.5.3") == 0.999 and gsplat_alpha_max("1.4.0") == 0.999
    assert gsplat_alpha_max("1.6.0") == 0.99 and gsplat_alpha_max("2.0.1") == 0.99


@pytest.mark.parametrize("version", ["1.5.3", "1.6.0"])
def test_gsplat_adaptor_conventions_on_cpu(monkeypatch, version):
    """The plug-in's marshalling (shapes, background, depth channel, visibility, the straight-through
    opacity cap for 0.999-clamping releases) against a stand-in that renders with the project splatter."""
    seen: dict = {}
    monkeypatch.setattr(rasterizers, "_import_gsplat", lambda: _fake_gsplat(version, seen))
    (means, scales, rotations, opacities, colors), cam = _scene()
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


def test_a_plugin_rasterizer_goes_first():
    class Counting(Rasterizer):
        """Counts renders, then splats with the torch splatter."""

        name = "counting"
        calls = 0

        def unavailable(self, device, dtype):
            return None

        def __call__(self, *args):
            Counting.calls += 1
            return TorchSplatter()(*args)

    class Plugin:
        @hookimpl
        def controlgs_register_rasterizers(self):
            return [Counting()]

    name = plugins.register_plugin(Plugin(), name="counting-rasterizer")
    try:
        assert list(plugins.rasterizers())[0] == "counting"
        scene, cam = _scene()
        rasterize_gaussians(*scene, cam)
        assert Counting.calls == 1
    finally:
        plugins.unregister_plugin(name)
    assert "counting" not in plugins.rasterizers()


def _gsplat_on_gpu() -> str | None:
    if not torch.cuda.is_available():
        return "no GPU available in this run: gsplat vs project splatter agreement not run"
    mod = rasterizers._import_gsplat()
    return mod if isinstance(mod, str) else None


@pytest.mark.skipif(_gsplat_on_gpu() is not None, reason=str(_gsplat_on_gpu()))
def test_gsplat_agrees_with_the_project_splatter_on_cuda():
    """Images and gradients within the documented convention differences (docs/rendering.md): the
    footprint ring between 3 and 3.33 sigma holds splats of alpha <= o e^-4.5 < 0.0111."""
    leaves, cam = _scene(n=400, device="cuda", max_opacity=0.95)
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


@pytest.mark.skipif(not torch.cuda.is_available(), reason="no GPU available in this run: a training step on CUDA not run")
def test_a_training_step_runs_on_cuda():
    pytest.importorskip("skimage")
    from controlgs_adapter.backends.models.reference_model import NeuralGaussianModel
    from controlgs_adapter.scene import load_builtin_scene
    from controlgs_adapter.training import TrainConfig, Trainer

    scene = load_builtin_scene("ar", 16, views=4, test_every=4, samples=2)
    xyz, rgb = scene.points(0.25)
    model = NeuralGaussianModel.from_points(xyz, rgb, feat_dim=8, n_offsets=2, voxel_size=0.35,
                                            color_fit_steps=20).to("cuda")
    t = Trainer(model, scene.views("train"), TrainConfig(iterations=2, checkpoint_every=0))
    assert t.device.type == "cuda" and t.cgs.injector.conditions.is_cuda
    t.train(progress=False)
    assert all(torch.isfinite(torch.tensor(t.history)))
    t.cgs.unwrap()


def test_gsplat_opacity_cap_passes_the_gradient_straight_through(monkeypatch):
    """With a 0.999-clamping gsplat (< 1.6) the adaptor caps opacities at 0.99 straight-through: a splat
    above the cap gets the gradient the splatter gives at the capped value (not zero, as a plain clamp would)."""
    monkeypatch.setattr(rasterizers, "_import_gsplat", lambda: _fake_gsplat("1.5.3", {}))
    (means, scales, rotations, opacities, colors), cam = _scene(seed=3)
    opacities[::3] = 0.9995
    opacities.requires_grad_(True)
    GsplatRasterizer()(means, scales, rotations, opacities, colors, cam).color.sum().backward()
    capped = opacities.detach().clamp(max=ALPHA_MAX).requires_grad_(True)
    rasterize(means, scales, rotations, capped, colors, cam).color.sum().backward()
    above = opacities.detach() > ALPHA_MAX
    assert bool(above.any()) and bool((capped.grad[above] != 0).any())
    torch.testing.assert_close(opacities.grad, capped.grad, rtol=1e-5, atol=1e-6)


@pytest.mark.parametrize("with_background", [True, False])
def test_gsplat_empty_render_stays_in_the_graph_like_the_torch_splatter(monkeypatch, with_background):
    """A view with no Gaussians (all culled by the decoder) renders the background; its loss must
    back-propagate (zero gradients of the empty inputs), as with the torch splatter, not raise
    "element 0 of tensors does not require grad" at ``loss.backward()`` in a CUDA training step."""
    monkeypatch.setattr(rasterizers, "_import_gsplat", lambda: _fake_gsplat("1.5.3", {}))
    (means, scales, rotations, opacities, colors), cam = _scene()
    bg = torch.tensor([0.2, 0.3, 0.4]) if with_background else None
    for r in (TorchSplatter(), GsplatRasterizer()):
        xs = [t[:0].clone().requires_grad_(True) for t in (means, scales, rotations, opacities, colors)]
        out = r(*xs, cam, bg)
        want = torch.zeros(3, 32, 48) if bg is None else bg.view(3, 1, 1).expand(3, 32, 48)
        assert torch.equal(out.color, want) and torch.equal(out.alpha, torch.zeros(1, 32, 48)), r.name
        assert out.color.requires_grad and out.alpha.requires_grad, r.name
        ((out.color - 1).square().sum() + out.alpha.sum()).backward()
        assert [tuple(x.grad.shape) for x in xs] == [(0, 3), (0, 3), (0, 4), (0,), (0, 3)], r.name
