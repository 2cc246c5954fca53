"""Tiny run folders and scenes for tests of the ``controlgs`` commands: a COLMAP capture of the built-in
scene at 24 px, an untrained adapter of the built-in backbone, a renderer module that leaves a marker
file when its code runs, and helpers to read the one error line and compare folders byte for byte."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import pytest

from controlgs_adapter.scene import builtin_backbone_dir

#: the built-in AR backbone's Scaffold-GS folder (a user's model folder in these tests)
MODEL = builtin_backbone_dir("ar")
#: training options that keep a run to seconds
FAST = ["--effects", "resample,display", "--no-progress", "--checkpoint-every", "0", "--no-ablations",
        "--resolution", "24"]

#: a renderer module whose code, when run, writes ``<module>.ran`` beside it; ``renderer`` is the model's own
MARKER_MODULE = '''
from pathlib import Path

Path(__file__).with_suffix(".ran").write_text("imported")


class OwnRenderer:
    def visible(self, model, camera):
        return model.visible_anchors(camera)

    def render(self, model, camera, visible, background):
        return model.render(camera, visible, background).color


renderer = OwnRenderer()
'''


def write_tiny_colmap(root: Path) -> Path:
    """A COLMAP capture (1 test, 5 training views at 24 px) of the built-in AR scene under ``root``."""
    from helpers.scene_writers import write_colmap

    from controlgs_adapter.scene import load_builtin_scene

    scene = load_builtin_scene("ar", 24, views=6, test_every=6, samples=1)
    return write_colmap(root / "colmap", scene.test_cameras + scene.train_cameras,
                        list(scene.test_images) + list(scene.train_images))


def untrained_run(run: Path, record: dict[str, Any] | None = None) -> Path:
    """A run folder holding an untrained (zero) ControlGS adapter of the built-in AR backbone and,
    if given, ``record`` as its run.json."""
    from controlgs_adapter import ControlGS
    from controlgs_adapter.scene import load_builtin_backbone

    run.mkdir(parents=True, exist_ok=True)
    cgs = ControlGS.wrap(load_builtin_backbone("ar"), cond_dim=2)
    cgs.save(run / "controlgs.controlgs.safetensors")
    cgs.unwrap()
    if record is not None:
        (run / "run.json").write_text(json.dumps(record))
    return run


def error_line(capsys: pytest.CaptureFixture[str], command: str) -> str:
    """The one line a refused ``controlgs <command>`` printed (asserted: one line, the CLI's prefix)."""
    err = capsys.readouterr().err.strip().splitlines()
    prefix = f"controlgs {command}: error: "
    assert len(err) == 1 and err[0].startswith(prefix), err
    return err[0][len(prefix):]


def snapshot(folder: Path) -> dict[str, bytes]:
    """Every file under ``folder`` (relative path -> bytes); empty when it does not exist."""
    if not folder.exists():
        return {}
    return {str(p.relative_to(folder)): p.read_bytes() for p in sorted(folder.rglob("*")) if p.is_file()}


needs_backbone = pytest.mark.skipif(not (MODEL / "point_cloud").is_dir(), reason="built-in backbone not baked")


def timings_within(info: dict[str, Any], keys: tuple[str, ...], wall: float) -> None:
    """The durations a command reports (seconds, one decimal) are each >= 0 and together at most the command's
    wall time (measured around it), allowing for the rounding of each."""
    got = [info[k] for k in keys]
    assert all(isinstance(v, float) and v >= 0 for v in got), info
    assert sum(got) <= wall + 0.05 * len(keys), (got, wall)
