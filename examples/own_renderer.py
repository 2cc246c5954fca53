"""Train an adapter on a model object the library did not create, rendered by your own code.

``MyGaussianModel`` stands for Scaffold-GS's ``GaussianModel``: a plain Python object (not an
``nn.Module``) whose decoders are TorchScript traces, as a Scaffold-GS checkpoint loads them.
``my_prefilter`` and ``my_render`` stand for its own renderer (here a few lines of Scaffold-GS's
decoding that splat with the library's rasterizer; the real one would call its CUDA code). The
library only sees them through the render protocol (docs/how-to/own-renderer.md) and gives them the same
training loop as its own families: state sampling, the PSF schedule, checkpoints and resume.

    python examples/own_renderer.py
"""

from __future__ import annotations

import copy
import io
import tempfile
import warnings
from pathlib import Path

import torch
import torch.nn.functional as F
from torch import nn

from controlgs_adapter import Camera
from controlgs_adapter.backends.scaffold_io import load_scaffold_dir
from controlgs_adapter.errors import InjectionMissedError
from controlgs_adapter.rendering.rasterizers import rasterize_gaussians
from controlgs_adapter.rendering.protocol import FunctionRenderer, render_view
from controlgs_adapter.scene import builtin_backbone_dir, load_builtin_scene
from controlgs_adapter.training import TrainConfig, Trainer

EFFECTS = {"lens": True, "resample": True, "display": True, "oled": True, "optics": True}


def _traced(mlp: nn.Module) -> torch.jit.ScriptModule:
    """``mlp`` saved and reloaded as a TorchScript trace (what ``torch.jit.load`` gives Scaffold-GS)."""
    buf = io.BytesIO()
    with warnings.catch_warnings():  # torch >= 2.10 deprecates TorchScript; checkpoints still use it
        warnings.simplefilter("ignore", DeprecationWarning)
        torch.jit.save(torch.jit.trace(mlp, torch.zeros(2, mlp[0].in_features)), buf)
        buf.seek(0)
        return torch.jit.load(buf)


class MyGaussianModel:
    """Scaffold-GS's layout: anchors ``_anchor [A, 3]``, features ``_anchor_feat [A, F]``, offsets
    ``_offset [A, K, 3]``, log-scales ``_scaling [A, 6]`` and the decoders ``mlp_opacity``,
    ``mlp_cov``, ``mlp_color`` (input: feature + view direction, ``F + 3``)."""

    def __init__(self, anchor: torch.Tensor, anchor_feat: torch.Tensor, offset: torch.Tensor, scaling: torch.Tensor,
                 decoders: dict[str, nn.Module]) -> None:
        self._anchor, self._anchor_feat, self._offset, self._scaling = anchor, anchor_feat, offset, scaling
        self.n_offsets = offset.shape[1]
        self.mlp_opacity, self.mlp_cov, self.mlp_color = (_traced(decoders[k]) for k in ("mlp_opacity", "mlp_cov", "mlp_color"))

    @property
    def get_anchor(self) -> torch.Tensor:
        return self._anchor

    @property
    def get_scaling(self) -> torch.Tensor:
        return torch.exp(self._scaling)


def my_prefilter(pc: MyGaussianModel, camera: Camera) -> torch.Tensor:
    """``BoolTensor[A]``: anchors in front of the camera (a coarser rule than Scaffold-GS's; any mask works)."""
    return camera.to_camera(pc.get_anchor)[:, 2] > 0.2


def my_render(pc: MyGaussianModel, camera: Camera, visible_mask: torch.Tensor, background: torch.Tensor) -> dict:
    """Scaffold-GS's ``generate_neural_gaussians`` + splatting, returning ``{"render": [3, H, W]}``."""
    anchor, feat = pc.get_anchor[visible_mask], pc._anchor_feat[visible_mask]  # [R, 3], [R, F]
    view = anchor - camera.center.to(anchor)
    x = torch.cat([feat, view / view.norm(dim=1, keepdim=True)], dim=1)  # [R, F + 3]: the decoders' rows
    opacity = pc.mlp_opacity(x).reshape(-1)  # [R*K]
    color = pc.mlp_color(x).reshape(-1, 3)
    scale_rot = pc.mlp_cov(x).reshape(-1, 7)
    keep = (opacity > 0).nonzero().squeeze(1)  # [G]
    row = keep // pc.n_offsets
    scaling = pc.get_scaling[visible_mask][row]  # [G, 6]
    means = anchor[row] + pc._offset[visible_mask].reshape(-1, 3)[keep] * scaling[:, :3]
    scales = scaling[:, 3:] * torch.sigmoid(scale_rot[keep, :3])
    rotations = F.normalize(scale_rot[keep, 3:7], dim=-1)
    out = rasterize_gaussians(means, scales, rotations, opacity[keep], color[keep], camera, background)
    return {"render": out.color, "visibility_filter": out.visible}


def main() -> None:
    scene = load_builtin_scene("ar", resolution=32, views=8, test_every=4)
    ref = load_scaffold_dir(builtin_backbone_dir("ar"))  # only to fill MyGaussianModel with trained values
    model = MyGaussianModel(ref._anchor.detach(), ref._anchor_feat.detach(), ref._offset.detach(), ref._scaling.detach(),
                            {k: getattr(ref, k) for k in ("mlp_opacity", "mlp_cov", "mlp_color")})
    renderer = FunctionRenderer(my_render, visible=my_prefilter)
    cam, _ = scene.views("test")[0]
    with torch.no_grad():
        own = render_view(None, model, cam, None, scene.background, renderer=renderer)
        lib = ref.render(cam, my_prefilter(model, cam), scene.background).color
    print(f"own render vs the library's reference model: max |diff| {float((own - lib).abs().max()):.2e}")

    with tempfile.TemporaryDirectory() as tmp:
        ckpt = Path(tmp) / "run.ckpt.safetensors"
        config = TrainConfig(iterations=4, checkpoint_every=2, psf_fraction=0.5)
        trainer = Trainer(model, scene.views("train"), config, effects=EFFECTS, renderer=renderer, checkpoint=ckpt)
        print(f"wrapped in place: {type(model.mlp_opacity).__name__} decoders on the user's object")
        trainer.train(until=2, progress=False)  # "interrupted" after 2 of 4 iterations; checkpoint written
        trainer.cgs.unwrap()
        trainer = Trainer(model, scene.views("train"), config, effects=EFFECTS, renderer=renderer, checkpoint=ckpt)
        trainer.resume()
        trainer.train(progress=False)
        for i, loss in enumerate(trainer.history):
            print(f"step {i}: loss {loss:.4f}")
        with torch.no_grad():
            wrapped = render_view(trainer.cgs, model, cam, trainer.sample()[1], scene.background, renderer=renderer)
        print(f"adapter changes the own render: max |diff| {float((wrapped - own).abs().max()):.2e}")
        trainer.cgs.unwrap()

    # wrapping one object and rendering another misses the injection: caught, naming the decoders
    trainer = Trainer(copy.copy(model), scene.views("train"), config, effects=EFFECTS,
                      renderer=FunctionRenderer(lambda _, c, v, bg: my_render(model, c, v, bg), visible=my_prefilter))
    try:
        trainer.step()
    except InjectionMissedError as e:
        print(f"injection missed: caught ({str(e)[:72]}...)")
    finally:
        trainer.cgs.unwrap()


if __name__ == "__main__":
    main()
