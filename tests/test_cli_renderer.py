"""``--rasterizer`` and ``--renderer`` of ``controlgs train`` / ``eval`` end to end on a tiny user
scene: a renderer module written by the user renders every training and evaluation view (it logs
its calls), the rasterizer choice takes effect (``$CONTROLGS_RASTERIZER`` names one that cannot run
here, so a run that ignored ``--rasterizer torch`` would fail), both are recorded in ``run.json`` and
``eval`` takes them from there (the renderer with ``--trust-run-renderer``); bad names fail in one
line naming what is available."""

from __future__ import annotations

import json

import pytest

pytest.importorskip("skimage")
pytest.importorskip("matplotlib")

from _scene_writers import write_colmap
from controlgs_adapter.cli import main
from controlgs_adapter.rendering.rasterizers import RASTERIZER_ENV
from controlgs_adapter.scene import builtin_backbone_dir, load_builtin_scene

MODEL = builtin_backbone_dir("ar")
pytestmark = pytest.mark.skipif(not (MODEL / "point_cloud").is_dir(), reason="built-in backbone not baked")
FAST = ["--effects", "resample,display", "--no-progress", "--checkpoint-every", "0", "--no-ablations"]

USER_MODULE = '''
from pathlib import Path

LOG = Path(__file__).with_suffix(".calls")


def _log(what):
    with LOG.open("a") as f:
        f.write(what + "\\n")


class CountingRenderer:
    """The model's own prefilter and render, logging each call."""

    def visible(self, model, camera):
        _log("visible")
        return model.visible_anchors(camera)

    def render(self, model, camera, visible, background):
        _log("render")
        return model.render(camera, visible, background).color


renderer = CountingRenderer()


def render_all(model, camera, visible, background):
    _log("function")
    return model.render(camera, visible, background)


def wrong_arguments(model, camera):
    return None


number = 3
'''


@pytest.fixture(scope="module")
def data(tmp_path_factory):
    scene = load_builtin_scene("ar", 24, views=6, test_every=6, samples=1)
    root = tmp_path_factory.mktemp("scene")
    return write_colmap(root / "colmap", scene.test_cameras + scene.train_cameras,
                        list(scene.test_images) + list(scene.train_images))


def _calls(log):
    return log.read_text().split() if log.is_file() else []


def test_user_renderer_and_rasterizer_train_and_evaluate(tmp_path, data, monkeypatch):
    module = tmp_path / "my_render.py"
    module.write_text(USER_MODULE)
    log = module.with_suffix(".calls")
    monkeypatch.setenv(RASTERIZER_ENV, "gsplat")  # ignored by a run that passes --rasterizer torch; fatal on CPU otherwise
    run, report = tmp_path / "run", tmp_path / "report"
    assert main(["train", "--model", str(MODEL), "--data", str(data), "--out", str(run), "--iterations", "3",
                 "--resolution", "24", *FAST, "--rasterizer", "torch", "--renderer", f"{module}:renderer"]) == 0
    record = json.loads((run / "run.json").read_text())
    assert record["renderer"] == f"{module.resolve()}:renderer" and record["rasterizer"] == "torch"
    trained = _calls(log)
    assert trained.count("render") == 3 and trained.count("visible") == 3  # one render per training step

    assert main(["eval", "--run", str(run), "--out", str(report), "--test-views", "1", "--no-progress"]) == 2
    assert _calls(log) == trained  # the run's renderer is not run without the user's say
    assert main(["eval", "--run", str(run), "--out", str(report), "--test-views", "1", "--no-progress",
                 "--trust-run-renderer"]) == 0
    evaluated = _calls(log)[len(trained):]
    assert evaluated.count("render") > 20  # the grid's renders (4 x 5 states, baselines) went through it
    info = json.loads((report / "results.json").read_text())["info"]
    assert info["renderer"] == record["renderer"] and info["rasterizer"] == "torch"

    # without the recorded choice the environment's gsplat applies, and cannot render on the CPU
    (run / "run.json").write_text(json.dumps({**record, "rasterizer": "auto"}))
    assert main(["eval", "--run", str(run), "--out", str(report), "--test-views", "1", "--no-progress",
                 "--trust-run-renderer"]) == 2


def test_a_render_function_from_the_current_folder(tmp_path, data, monkeypatch, capsys):
    (tmp_path / "my_render_fn.py").write_text(USER_MODULE)
    monkeypatch.chdir(tmp_path)  # MODULE:ATTR is found in the current folder, as `python -m` would
    assert main(["train", "--model", str(MODEL), "--data", str(data), "--out", str(tmp_path / "run"), "--iterations", "2",
                 "--resolution", "24", *FAST, "--renderer", "my_render_fn:render_all"]) == 0
    assert _calls(tmp_path / "my_render_fn.calls") == ["function", "function"]
    record = json.loads((tmp_path / "run" / "run.json").read_text())
    assert record["renderer"] == "my_render_fn:render_all" and record["rasterizer"] == "auto"


@pytest.mark.parametrize("option, expected", [
    (["--rasterizer", "nvdiffrast"], "--rasterizer 'nvdiffrast' is not registered; available: "),
    (["--rasterizer", "gsplat"], "pip install 'controlgs-adapter[gsplat]'"),
    (["--renderer", "no_such_module_xyz:render"], "no module named 'no_such_module_xyz'"),
    (["--renderer", "my_render:missing"], "my_render has no attribute 'missing'"),
    (["--renderer", "my_render:CountingRenderer"], "CountingRenderer is a class"),
    (["--renderer", "my_render:wrong_arguments"], "wrong_arguments does not fit the render protocol"),
    (["--renderer", "my_render:number"], "number does not fit the render protocol"),
    (["--renderer", "my_render"], "--renderer must be MODULE:ATTR or path/to/file.py:ATTR"),
    (["--renderer", "nowhere/render.py:render"], "no such file nowhere/render.py"),
])
def test_bad_rasterizer_or_renderer_is_one_line(tmp_path, data, monkeypatch, capsys, option, expected):
    (tmp_path / "my_render.py").write_text(USER_MODULE)
    monkeypatch.chdir(tmp_path)
    code = main(["train", "--model", str(MODEL), "--data", str(data), "--out", str(tmp_path / "run"), "--iterations", "1",
                 "--resolution", "24", *FAST, *option])
    err = capsys.readouterr().err.strip()
    assert code == 2 and len(err.splitlines()) == 1 and expected in err, err
    if option[1] == "nvdiffrast":
        assert "torch" in err and "gsplat" in err
    assert not (tmp_path / "run" / "controlgs.controlgs.safetensors").exists()
