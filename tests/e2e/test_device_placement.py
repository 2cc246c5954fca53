"""The GPU path checked on the CPU: the training step, the pipeline with every stage in each optics mode,
the grid evaluation and the viewer's render run with the model on the guard's model device
(:mod:`helpers.device_guard`: the host and the model's device kept apart on one CPU), give the same numbers
as without the guard, and each of three device mistakes put back into the library is caught."""

from __future__ import annotations

import copy
import importlib.util
import subprocess
import zipfile
from pathlib import Path
from typing import Any

import pytest
import torch
from helpers.adapters import random_adapter
from helpers.device_guard import MODEL_DEVICE, DeviceGuard, DevicePlacementError, on_model, patch_everywhere, with_edit

from controlgs_adapter.downstream import display, warp
from controlgs_adapter.downstream.pipeline import Pipeline
from controlgs_adapter.evaluation import evaluate_grid
from controlgs_adapter.rendering import splatter
from controlgs_adapter.scene import load_builtin_backbone, load_builtin_scene, render_planes
from controlgs_adapter.state import RuntimeState
from controlgs_adapter.training import TrainConfig, Trainer
from controlgs_adapter.viewer.session import ViewerSession, ViewState

pytest.importorskip("skimage")  # the built-in scene

ROOT = Path(__file__).resolve().parents[2]

#: every stage; the optics mode is set per test
ALL = {"lens": True, "resample": True, "display": True, "oled": True}
MODES = ("distortion", "fast", "exact")


@pytest.fixture(scope="module")
def placed(tiny) -> tuple[Any, Any]:
    """``(scene, model)``: the tiny scene loaded as the commands load it (its tensors on the host) and a copy
    of ``tiny``'s backbone moved to the model's device."""
    with DeviceGuard():
        scene = load_builtin_scene("ar", 16, views=4, test_every=4, samples=1)
        model = copy.deepcopy(tiny[1]).to(MODEL_DEVICE)
    assert not on_model(scene.views("train")[0][1]) and all(on_model(p) for p in model.parameters())
    return scene, model


def _train(scene: Any, model: Any, device: Any, effects: dict[str, Any] | None = None, lens: Any = None,
           **config: Any) -> list[float]:
    """Two steps of a fresh adapter on a copy of ``model`` (on ``device``), the second one through the PSF."""
    t = Trainer(copy.deepcopy(model).to(device), scene.views("train"),
                TrainConfig(iterations=2, checkpoint_every=0, psf_fraction=0.5, seed=1, **config),
                effects={**ALL, "optics": {"mode": "distortion"}, **(effects or {})}, lens=lens)
    t.train(progress=False)
    t.cgs.unwrap()
    return t.history


def test_a_training_step_keeps_to_the_model_device(placed):
    scene, model = placed
    with DeviceGuard() as guard:
        guarded = _train(scene, model, MODEL_DEVICE)
    assert guard.made > 0  # the step makes host tensors (the view and state draws) and keeps them apart
    assert guarded == _train(scene, model, "cpu")


def test_a_foveated_training_step_in_the_lens_frame_keeps_to_the_model_device(placed):
    """The lens condition in its (x, y) frame (its field-map table), the foveation stage and condition (the gaze
    drawn through the lens's visual angles), through the compact lens."""
    scene, model = placed
    kw = dict(effects={"foveation": True}, lens="compact", lens_conditioning="xy", modules=("lens", "foveation"))
    with DeviceGuard():
        guarded = _train(scene, model, MODEL_DEVICE, **kw)
    assert guarded == _train(scene, model, "cpu", **kw)


@pytest.mark.parametrize("mode", MODES)
def test_the_pipeline_with_every_stage_keeps_to_the_model_device(mode):
    torch.manual_seed(0)
    image, gt = torch.rand(3, 16, 16, dtype=torch.float64), torch.rand(3, 16, 16, dtype=torch.float64)

    def run(device: Any) -> tuple[torch.Tensor, torch.Tensor]:
        p = Pipeline.from_config({**ALL, "optics": {"mode": mode}}).double().to(device)
        x = image.to(device).requires_grad_(True)
        out = p(x, RuntimeState(2.0, 0.3), reference=gt.to(device))
        (grad,) = torch.autograd.grad((out * out).sum(), x)
        return out.detach(), grad

    with DeviceGuard():
        out, grad = run(MODEL_DEVICE)
    ref_out, ref_grad = run("cpu")
    assert torch.equal(out, ref_out) and torch.equal(grad, ref_grad)


def test_the_grid_evaluation_keeps_to_the_model_device(placed, tmp_path):
    scene, model = placed
    adapter = random_adapter(model, tmp_path / "a.controlgs.safetensors", cond_dim=4)

    def run() -> dict[str, Any]:
        return evaluate_grid(model, scene.views("test"), {"controlgs": adapter}, downsample=(1.0, 2.0),
                             power_saving=(0.0, 0.4), optics_mode="fast", progress=False).to_json()

    with DeviceGuard():
        guarded = run()
    assert guarded == run()


def _session(adapter: Path, device: Any) -> ViewerSession:
    """A viewer session built as ``controlgs view`` builds one on the built-in scene, the backbone on ``device``."""
    scene = load_builtin_scene("ar", 16, views=4, test_every=4, samples=1)
    model = load_builtin_backbone("ar").to(device)
    background = tuple(scene.background.tolist())
    return ViewerSession(model, scene.views("test"), {"controlgs": adapter},
                         truth=lambda cam: render_planes(scene.planes, cam, background=background, samples=1)[0].float())


def test_the_viewer_render_keeps_to_the_model_device(tmp_path):
    adapter = random_adapter(load_builtin_backbone("ar"), tmp_path / "v.controlgs.safetensors", 3, cond_dim=4)
    states = [ViewState(), ViewState(optics="exact"), ViewState(azimuth=10.0, elevation=5.0, optics="distortion")]
    with DeviceGuard():
        session = _session(adapter, MODEL_DEVICE)
        guarded = [session.render(s) for s in states]
    plain = _session(adapter, "cpu")
    for a, b in zip(guarded, (plain.render(s) for s in states)):
        del a["server_ms"], b["server_ms"]
        assert a == b


# ----------------------------------------------------------------------------- the guard catches each mistake
#: (function, code with device=, the same without, what runs it): a dropped device= of an index table (the
#: splatter's owner of each tile record), of an arange (the pixel grid of the lens pre-warp) and of a tensor
#: built from a Python list (the display's luminance weights)
MISTAKES = [
    (splatter._bin_tiles, "torch.arange(ids.numel(), device=dev)", "torch.arange(ids.numel())", "train"),
    (warp.pixel_grid, "torch.arange(h, dtype=dtype, device=device)", "torch.arange(h, dtype=dtype)", "pipeline"),
    (display._power, "torch.tensor(c, dtype=linear.dtype, device=linear.device)", "torch.tensor(c, dtype=linear.dtype)",
     "pipeline"),
]


def _workload(where: str, scene: Any, model: Any, device: Any) -> None:
    if where == "train":
        _train(scene, model, device)
    else:
        p = Pipeline.from_config({**ALL, "optics": {"mode": "distortion"}}).to(device)
        p(torch.rand(3, 16, 16, device=device), RuntimeState(2.0, 0.3))


@pytest.mark.parametrize("func, old, new, where", MISTAKES, ids=[m[0].__name__ for m in MISTAKES])
def test_a_dropped_device_is_caught(placed, monkeypatch, func, old, new, where):
    """Each mistake runs on the CPU as it stands and fails under the guard, naming the line."""
    assert patch_everywhere(monkeypatch, func, with_edit(func, old, new)) >= 1
    scene, model = placed
    _workload(where, scene, model, "cpu")
    with pytest.raises(DevicePlacementError, match=rf"made at .*{Path(func.__code__.co_filename).name}:\d+"):
        with DeviceGuard():
            _workload(where, scene, model, MODEL_DEVICE)


# ----------------------------------------------------------------------------- the prepared device check
def _gpu_check() -> Any:
    spec = importlib.util.spec_from_file_location("gpu_check", ROOT / "scripts" / "gpu_check.py")
    assert spec is not None and spec.loader is not None
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def test_the_device_check_command_lines_parse(tmp_path, monkeypatch):
    """Every command line of ``scripts/gpu_check.py`` (controlgs, torchrun, the step benchmark, on cpu and cuda)
    parses, and one that does not is named."""
    check = _gpu_check()
    assert check.parse_problems(tmp_path) == []
    good = check.commands
    monkeypatch.setattr(check, "commands", lambda *a: {**good(*a), "bad": ["train", "--iterations", "many"]})
    assert check.parse_problems(tmp_path) == ["controlgs train --iterations many: argparse refused it (exit 2)"] * 2


def _wheel(folder: Path, name: str, version: str, requires: list[str]) -> None:
    with zipfile.ZipFile(folder / f"{name}-{version}-py3-none-any.whl", "w") as z:
        z.writestr(f"{name}-{version}.dist-info/METADATA", "Metadata-Version: 2.1\nName: {name}\nVersion: {version}\n"
                   + "".join(f"Requires-Dist: {r}\n" for r in requires))


def test_the_device_check_names_each_missing_wheel(tmp_path):
    """One line per requirement no carried wheel satisfies, following the carried wheels' own dependencies
    for Linux x86_64 Python 3.11 (a local version like +cu126 satisfies ==)."""
    check = _gpu_check()
    _wheel(tmp_path, "torch", "2.13.0+cu126", ["nvidia_cudnn_cu12==9.1; platform_system == 'Linux'",
                                               "pywin32; sys_platform == 'win32'", "filelock"])
    _wheel(tmp_path, "filelock", "3.0", [])
    _wheel(tmp_path, "gsplat", "1.3.0", [])
    assert check.missing_wheels(tmp_path, ["torch==2.13.0", "gsplat>=1.4", "rich"]) == [
        "missing wheel: gsplat>=1.4 (requested)",
        "missing wheel: nvidia_cudnn_cu12==9.1 (needed by torch-2.13.0+cu126-py3-none-any.whl)",
        "missing wheel: rich (requested)"]
    _wheel(tmp_path, "nvidia_cudnn_cu12", "9.1", [])
    _wheel(tmp_path, "gsplat", "1.5.3", ["jaxtyping"])
    _wheel(tmp_path, "jaxtyping", "0.2", [])
    _wheel(tmp_path, "rich", "13", [])
    assert check.missing_wheels(tmp_path, ["torch==2.13.0", "gsplat>=1.4", "rich"]) == []


def test_the_device_check_script_refuses_an_unknown_argument():
    res = subprocess.run(["bash", str(ROOT / "scripts" / "gpu_check.sh"), "--bogus"], capture_output=True, text=True,
                         timeout=60)
    assert res.returncode == 2 and "unknown argument --bogus" in res.stderr
