"""The render protocol: the families' own renderer, user renderers (objects and functions), the
injection staying on the user's object (TorchScript decoders included), misses caught, and the
training step's host syncs counted."""

import collections
import copy
import traceback

import pytest
import torch
from torch.utils._python_dispatch import TorchDispatchMode

from controlgs_adapter import ControlGS, RuntimeState
from controlgs_adapter.errors import InjectionMissedError, InputValueError, ShapeError
from controlgs_adapter.rendering.protocol import (FunctionRenderer, ModelRenderer, Renderer, as_renderer, model_device,
                                         render_view, renderer_for)
from scaffold_standin import ScaffoldStandIn, make_camera, script_decoders

pytest.importorskip("skimage")

from controlgs_adapter.backends.models.reference_model import NeuralGaussianModel  # noqa: E402
from controlgs_adapter.scene import load_builtin_scene  # noqa: E402
from controlgs_adapter.training import TrainConfig, Trainer  # noqa: E402

EFFECTS = {"lens": True, "resample": True, "display": True, "oled": True, "optics": {"mode": "distortion"}}
STATE = RuntimeState(downsample=2, power_saving=0.4)


@pytest.fixture(scope="module")
def tiny():
    scene = load_builtin_scene("ar", 16, views=4, test_every=4, samples=2)
    torch.manual_seed(0)  # from_points draws from the global generator: the same model whatever ran before
    xyz, rgb = scene.points(0.25)
    model = NeuralGaussianModel.from_points(xyz, rgb, feat_dim=8, n_offsets=2, voxel_size=0.35, color_fit_steps=20)
    return scene, model.eval()


def _config(**kw):
    return TrainConfig(**{"iterations": 3, "checkpoint_every": 0, "psf_fraction": 0.34, **kw})


def test_loaded_models_render_through_their_own_renderer(tiny):
    scene, model = tiny
    r = renderer_for(model)
    assert type(r) is ModelRenderer and isinstance(r, Renderer) and as_renderer(None, model) is not None
    cam = scene.test_cameras[0]
    with torch.no_grad():
        want = model.render(cam, model.visible_anchors(cam), scene.background).color
        assert torch.equal(render_view(None, model, cam, None, scene.background), want)


def test_a_user_renderer_gets_the_same_training(tiny):
    """A function renderer doing what the model's own does trains to the same adapter, bit for bit."""
    scene, model = tiny
    views = scene.views("train")
    own = FunctionRenderer(lambda m, c, v, bg: m.render(c, v, bg), visible=lambda m, c: m.visible_anchors(c))

    class Obj:  # an object following the protocol
        def visible(self, m, c):
            return m.visible_anchors(c)

        def render(self, m, c, v, bg):
            return m.render(c, v, bg).color

    runs = []
    for renderer in (None, own, Obj()):
        t = Trainer(model, views, _config(), effects=EFFECTS, renderer=renderer)
        t.train(progress=False)
        runs.append((list(t.history), {k: v.clone() for k, v in t.cgs.injector.state_dict().items()}))
        t.cgs.unwrap()
    for history, state in runs[1:]:
        assert history == runs[0][0]
        assert all(torch.equal(state[k], runs[0][1][k]) for k in state)


def test_render_of_another_object_is_caught(tiny):
    scene, model = tiny
    cam = scene.test_cameras[0]
    other = copy.deepcopy(model)  # e.g. a copy made before wrapping: its decoders carry no hooks
    cgs = ControlGS.wrap(model)
    try:
        stale = FunctionRenderer(lambda m, c, v, bg: other.render(c, v, bg), visible=lambda m, c: m.visible_anchors(c))
        with pytest.raises(InjectionMissedError, match=r"mlp_opacity\.0, mlp_cov\.0, mlp_color\.0"):
            render_view(cgs, model, cam, STATE, scene.background, renderer=stale)
        with pytest.warns(RuntimeWarning, match="no wrapped decoder ran"), torch.no_grad():
            with cgs.conditioned(STATE, cam, model.visible_anchors(cam)):
                other.render(cam, model.visible_anchors(cam))
        with pytest.raises(InputValueError, match="on_miss"):
            with cgs.conditioned(STATE, cam, on_miss="sometimes"):
                pass
        render_view(cgs, model, cam, STATE, scene.background)  # the wrapped object itself: fine
    finally:
        cgs.unwrap()


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
    with torch.no_grad(), cgs.conditioned(STATE, cam):
        after = model.decode(x)
        assert cgs.injector.context.calls == {"mlp_opacity": 1, "mlp_cov": 1, "mlp_color": 1}
    assert not torch.equal(after["color"], before["color"])
    cam3 = make_camera(width=10, height=3)
    with torch.no_grad():
        image = render_view(cgs, model, cam3, STATE, renderer=renderer)
    assert image.shape == (3, 3, 10)
    cgs.unwrap()
    assert all(getattr(model, k) is v for k, v in originals.items())


def test_renderer_errors(tiny):
    scene, model = tiny
    with pytest.raises(InputValueError, match="renderer="):
        renderer_for(ScaffoldStandIn(num_anchors=5))  # Scaffold-GS's GaussianModel renders with outside code
    with pytest.raises(InputValueError, match="renderer must be"):
        as_renderer(42, model)
    with pytest.raises(InputValueError, match="callables"):
        FunctionRenderer(lambda *a: None, visible="mask")
    cam = scene.test_cameras[0]
    with pytest.raises(ShapeError, match=r"expected an sRGB image \[3, 16, 16\]"):
        render_view(None, model, cam, None, renderer=lambda m, c, v, bg: torch.zeros(3, 8, 8))


def test_model_device_of_a_plain_object():
    assert model_device(ScaffoldStandIn(num_anchors=5)) == torch.device("cpu")
    assert model_device(object()) == torch.device("cpu")
    assert model_device(torch.nn.Linear(2, 2).to(torch.device("meta"))) == torch.device("meta")

    class Plain:
        def __init__(self):
            self.mlp = torch.nn.Linear(2, 2, device="meta")

    assert model_device(Plain()) == torch.device("meta")


class _HostSyncs(TorchDispatchMode):
    """Counts ``aten._local_scalar_dense`` (a tensor value read on the host: ``.item()``,
    ``float(t)``, ``bool(t)``), each with the library frames that asked for it."""

    def __init__(self) -> None:
        super().__init__()
        self.calls: list[list[str]] = []

    def __torch_dispatch__(self, func, types, args=(), kwargs=None):
        if func.overloadpacket is torch.ops.aten._local_scalar_dense:
            frames = [f for f in traceback.extract_stack()[:-1] if "site-packages" not in f.filename]
            self.calls.append([f"{f.filename}:{f.name}: {f.line}" for f in frames])
        return func(*args, **(kwargs or {}))


def test_training_step_host_syncs(tiny):
    """Host syncs of one training step outside the loss log: the view/state sampling (a CPU
    generator) and Adam's step counters are host tensors on any device; the pure-torch splatter's
    own input checks are the rasterizer's (gsplat has none). Everything else: at most 2 (now 1:
    the parameter check)."""
    scene, model = tiny
    t = Trainer(model, scene.views("train"), _config(), effects=EFFECTS)
    try:
        t.step()
        with _HostSyncs() as mode:
            t.step()
    finally:
        t.cgs.unwrap()
    kinds = collections.Counter()
    for stack in mode.calls:
        where = " ".join(stack)
        kind = ("sampling" if ":sample:" in where else "optimizer" if "optimizer.step()" in where else
                "rasterizer" if "controlgs_adapter/rendering/splatter.py" in where else
                "loss log" if stack[-1].endswith("value += float(loss.detach())  # the loss log: the step's one device "
                                                 "sync besides the check below") else "step")
        kinds[kind] += 1
    print("host syncs of one training step:", dict(kinds))
    assert kinds["loss log"] == 1 and kinds["step"] <= 2, dict(kinds)


def test_render_view_without_adapter_or_state_is_the_bare_backbone(tiny):
    scene, model = tiny
    cam = scene.test_cameras[0]
    with torch.no_grad():
        bare = model.render(cam, model.visible_anchors(cam), scene.background).color
        assert bare.amax() > 0.1  # the camera sees the scene
        cgs = ControlGS.wrap(model)
        try:
            gen = torch.Generator().manual_seed(0)
            for p in cgs.injector.parameters():  # an adapter that changes the decode
                p.add_(0.5 * torch.randn(p.shape, generator=gen))
            assert not torch.equal(render_view(cgs, model, cam, STATE, scene.background), bare)
            assert torch.equal(render_view(cgs, model, cam, None, scene.background), bare)  # no state: no condition
            assert torch.equal(render_view(None, model, cam, STATE, scene.background), bare)  # no adapter
        finally:
            cgs.unwrap()
