"""The README's quick start, runnable: wrap a Scaffold-GS model loaded from its output folder,
render under a run-time state, train a few adapter steps through the XR pipeline, save and reload.

    python examples/quickstart.py
"""

from __future__ import annotations

import tempfile
from pathlib import Path

import torch

from controlgs_adapter import ControlGS, RuntimeState
from controlgs_adapter.backends.scaffold_io import load_scaffold_dir
from controlgs_adapter.downstream import Pipeline
from controlgs_adapter.losses import image_loss
from controlgs_adapter.scene import builtin_backbone_dir, load_builtin_scene


def main() -> None:
    scene = load_builtin_scene("ar", resolution=64)
    model = load_scaffold_dir(builtin_backbone_dir("ar"))  # a Scaffold-GS output folder, no CUDA needed
    cgs = ControlGS.wrap(model)  # lens + resample + display conditions, zero-initialised
    print(cgs.summary())
    pipeline = Pipeline.from_config({"lens": True, "resample": True, "display": True, "optics": True})
    opt = torch.optim.Adam(cgs.trainable_parameters(), lr=3e-3)
    state = RuntimeState(downsample=4, power_saving=0.4)
    train = scene.views("train")  # a dataset like any other: views[i] = (camera, image [3, H, W])
    for step in range(5):
        cam, gt = train[step]
        visible = model.visible_anchors(cam)  # row i of the decoders = i-th visible anchor
        with cgs.conditioned(state, camera=cam, anchor_ids=visible):
            image = model.render(cam, visible, background=scene.background).color
        eye = pipeline(image.clamp(0, 1), state, reference=gt)
        loss = image_loss(eye, gt)
        opt.zero_grad()
        loss.backward()
        opt.step()
        print(f"step {step}: loss {float(loss.detach()):.4f}")
    path = Path(tempfile.mkdtemp()) / "ar.controlgs.safetensors"
    cgs.save(path)
    model = cgs.unwrap()
    reloaded = ControlGS.load(path, model)
    print(f"saved and reloaded {path} ({path.stat().st_size / 1024:.0f} KiB): {reloaded!r}")


if __name__ == "__main__":
    main()
