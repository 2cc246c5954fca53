"""The README's quick start, runnable: wrap a Scaffold-GS model loaded from its output folder,
render under a run-time state, train a few adapter steps through the XR pipeline, save and reload.

    python examples/quickstart.py
"""

from __future__ import annotations

import tempfile
from pathlib import Path

from controlgs_adapter import ControlGS, RuntimeState
from controlgs_adapter.backends.scaffold_io import load_scaffold_dir
from controlgs_adapter.scene import builtin_backbone_dir, load_builtin_scene
from controlgs_adapter.training import TrainConfig, Trainer


def main() -> None:
    scene = load_builtin_scene("ar", resolution=64)
    model = load_scaffold_dir(builtin_backbone_dir("ar"))  # a Scaffold-GS output folder, no CUDA needed
    train = scene.views("train")  # a dataset like any other: views[i] = (camera, image [3, H, W])
    cgs = ControlGS.wrap(model)  # lens + resample + display conditions, zero-initialised
    print(cgs.summary())
    cam, _ = train[0]
    visible = model.visible_anchors(cam)  # row i of the decoders = i-th visible anchor
    with cgs.conditioned(RuntimeState(downsample=4, power_saving=0.4), camera=cam, anchor_ids=visible):
        image = model.render(cam, visible, background=scene.background).color  # [3, H, W] sRGB
    print(f"rendered {list(image.shape)} under d=4, rho=0.4")
    model = cgs.unwrap()
    # a few steps of the library's one training step (render -> lens, resample, display, optics -> loss):
    # Trainer wraps the model, samples (view, state) and owns the optimizer over the adapter only
    trainer = Trainer(model, train, TrainConfig(iterations=5, checkpoint_every=0))
    for step in range(5):
        print(f"step {step}: loss {trainer.step():.4f}")
    path = Path(tempfile.mkdtemp()) / "ar.controlgs.safetensors"
    trainer.cgs.save(path)
    model = trainer.cgs.unwrap()
    reloaded = ControlGS.load(path, model)
    print(f"saved and reloaded {path} ({path.stat().st_size / 1024:.0f} KiB): {reloaded!r}")


if __name__ == "__main__":
    main()
