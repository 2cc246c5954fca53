"""Tests of ``controlgs_adapter.commands.view``: its defaults, the adapters and ground truth it serves, the session it
builds for the built-in scene or a user's run (the server's loop replaced by renders), and what it refuses in one
line before the viewer is built: a renderer the run names unless named again or trusted, a hand-edited run file,
bad options."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import pytest
import torch
from helpers.adapters import random_adapter
from helpers.cli_runs import MARKER_MODULE, MODEL, error_line, needs_backbone, snapshot, untrained_run
from helpers.scene_writers import write_colmap
from helpers.viewer_sessions import decode_png

from controlgs_adapter import ControlGS, cli
from controlgs_adapter.backends import load_model_dir
from controlgs_adapter.cli import main
from controlgs_adapter.commands.view import QUICK_ITERATIONS, VIEW_RESOLUTION, _adapters, _exact_truth
from controlgs_adapter.errors import InputValueError
from controlgs_adapter.scene import load_builtin_backbone, load_builtin_scene
from controlgs_adapter.state import Camera
from controlgs_adapter.viewer import parse_state
from controlgs_adapter.viewer.server import ViewerServer

RECORD = {"variant": "ar", "effects": ["display"], "iterations": 7, "seed": 0, "seeds": 1, "adapters": ["controlgs"],
          "rasterizer": "auto"}
FAST = ["--threads", "1", "--resolution", "16", "--test-views", "1"]


@pytest.fixture
def served(monkeypatch: pytest.MonkeyPatch) -> list[Any]:
    """The sessions the command would have served (serve_forever returns at once)."""
    sessions: list[Any] = []

    def record(self: ViewerServer, poll_interval: float = 0.5) -> None:
        sessions.append(self.session)

    monkeypatch.setattr(ViewerServer, "serve_forever", record)
    return sessions


@pytest.fixture(scope="module")
def marked_run(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path, str]:
    """A built-in run whose run.json names a renderer file that leaves a marker when its code runs."""
    root = tmp_path_factory.mktemp("view")
    (root / "view_marker.py").write_text(MARKER_MODULE)
    spec = f"{root / 'view_marker.py'}:renderer"
    return untrained_run(root / "run", {**RECORD, "renderer": spec}), root / "view_marker.ran", spec


# ----------------------------------------------------------------------------- options, adapters and ground truth

def test_view_defaults() -> None:
    v = cli.build_parser().parse_args(["view"])
    assert (v.run, v.port, v.iterations, v.threads, v.resolution, v.test_views) == (None, 0, 150, None, None, None)
    args = cli.build_parser().parse_args(["view", "--port", "0", "--run", "somewhere"])
    assert args.command == "view" and args.port == 0 and args.run == "somewhere"
    assert (QUICK_ITERATIONS, VIEW_RESOLUTION) == (150, 128)


def test_view_adapters_of_a_run_folder(tmp_path):
    with pytest.raises(InputValueError, match=f"{tmp_path}: no controlgs.controlgs.safetensors"):
        _adapters(tmp_path)
    for n in ("controlgs", "state_blind", "other"):
        (tmp_path / f"{n}.controlgs.safetensors").write_text("")
    assert _adapters(tmp_path) == {"controlgs": tmp_path / "controlgs.controlgs.safetensors",
                                   "state_blind": tmp_path / "state_blind.controlgs.safetensors"}


def test_view_exact_truth_is_the_dataset_image():
    """``_exact_truth``: "the built-in scene's exact ground truth of any camera (ray cast, as its
    dataset's images)": a test camera's truth is its test image (float32, [3, H, W])."""
    for variant in ("ar", "vr"):
        builtin = load_builtin_scene(variant, 16, views=4, test_every=4)
        truth = _exact_truth(builtin)
        got = truth(builtin.test_cameras[0])
        assert got.dtype == torch.float32 and torch.equal(got, builtin.test_images[0]), variant


# ----------------------------------------------------------------------------- refusals before the viewer is built

@pytest.mark.parametrize("argv, start", [
    (["--threads", "0"], "--threads must be an integer in [1, 4096], got 0"),
    (["--threads", "9" * 40], "--threads must be an integer in [1, 4096], got "),
    (["--port", "65536"], "--port must be an integer in [0, 65535], got 65536"),
    (["--port", "70000"], "--port must be an integer in [0, 65535], got 70000"),
    (["--port", "-1"], "--port must be an integer in [0, 65535], got -1"),
    (["--model", "m", "--data", "d"], "--model/--data need --run RUN"),
    (["--rasterizer", "nope"], "--rasterizer 'nope' is not registered"),
    (["--run", "{d}/none"], "--run {d}/none: no such folder"),
    (["--run", "{d}", "--test-views", "1"], "{d}: no controlgs.controlgs.safetensors"),
])
def test_bad_options_are_one_line(tmp_path: Path, capsys: pytest.CaptureFixture[str], argv: list[str], start: str) -> None:
    d = str(tmp_path)
    assert main(["view", *[a.replace("{d}", d) for a in argv]]) == 2
    assert error_line(capsys, "view").startswith(start.replace("{d}", d))


@needs_backbone
def test_view_refuses_zero_quick_iterations(tmp_path, monkeypatch, capsys):
    """Without ``--run`` the built-in scene's quick adapter needs ``--iterations`` >= 1: refused on one
    line before any training (the server is never started)."""
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "cache"))
    monkeypatch.setattr(ViewerServer, "serve_forever", lambda self, poll_interval=0.5: None)
    assert main(["view", "--resolution", "16", "--iterations", "0"]) == 2
    assert error_line(capsys, "view").startswith("--iterations must be an integer in [1, ")


@needs_backbone
@pytest.mark.parametrize("option, value", [("--test-views", "0"), ("--test-views", "-3"), ("--resolution", "0"),
                                           ("--device", "meta"), ("--cache-mib", "-1")])
def test_a_bad_option_is_one_line_before_loading(tmp_path: Path, served: list[Any], capsys: pytest.CaptureFixture[str],
                                                 option: str, value: str) -> None:
    run = untrained_run(tmp_path / "run", RECORD)
    assert main(["view", "--run", str(run), *FAST, option, value]) == 2
    line = error_line(capsys, "view")
    assert line.startswith(f"{option} ") and value in line, line
    assert served == []


@needs_backbone
@pytest.mark.parametrize("record, field", [({**RECORD, "effects": 5}, "'effects'"),
                                           ({**RECORD, "resolution": -4}, "'resolution'"),
                                           ([RECORD], "a JSON list")])
def test_a_hand_edited_run_file_is_one_line(tmp_path: Path, served: list[Any], capsys: pytest.CaptureFixture[str],
                                            record: Any, field: str) -> None:
    run = untrained_run(tmp_path / "run")
    (run / "run.json").write_text(json.dumps(record))
    assert main(["view", "--run", str(run), *FAST]) == 2
    line = error_line(capsys, "view")
    assert line.startswith(f"{run / 'run.json'}: ") and field in line, line
    assert served == []


@needs_backbone
def test_the_run_renderer_is_not_run_without_the_users_say(marked_run: tuple[Path, Path, str], served: list[Any],
                                                           capsys: pytest.CaptureFixture[str]) -> None:
    run, marker, spec = marked_run
    marker.unlink(missing_ok=True)
    before = snapshot(run)
    assert main(["view", "--run", str(run), *FAST]) == 2
    line = error_line(capsys, "view")
    assert str(run / "run.json") in line and f"--renderer {spec}" in line and "--trust-run-renderer" in line, line
    assert not marker.exists() and served == [] and snapshot(run) == before


@needs_backbone
@pytest.mark.parametrize("how", [["--trust-run-renderer"], ["--renderer", "SPEC"]])
def test_the_run_renderer_is_used_when_trusted_or_named(marked_run: tuple[Path, Path, str], served: list[Any],
                                                        capsys: pytest.CaptureFixture[str], how: list[str]) -> None:
    run, marker, spec = marked_run
    marker.unlink(missing_ok=True)
    assert main(["view", "--run", str(run), *FAST, *[spec if a == "SPEC" else a for a in how]]) == 0
    assert marker.exists()
    (session,) = served
    assert type(session.renderer).__name__ == "OwnRenderer" and session.methods[-1] == "controlgs"
    assert "serving on http://127.0.0.1:" in capsys.readouterr().out


# ----------------------------------------------------------------------------- the session it serves

@needs_backbone
def test_view_of_the_built_in_scene_with_a_run(tmp_path, monkeypatch, capsys):
    """``controlgs view --run RUN`` on the built-in scene (RUN has no run.json): ``--resolution`` and
    ``--test-views`` reach the session, which carries the scene's name and the exact ground truth of any
    camera (an orbit view has one too, unlike a user's data); the server's loop is replaced by two renders."""
    run = tmp_path / "run"
    run.mkdir()
    cgs = ControlGS.wrap(load_builtin_backbone("ar"), cond_dim=2)  # zero conditions: renders as the backbone
    cgs.save(run / "controlgs.controlgs.safetensors")
    cgs.unwrap()
    seen: list[Any] = []

    def two_renders(self: ViewerServer, poll_interval: float = 0.5) -> None:
        n = len(self.session.cameras)
        seen.append((self.session, self.session.render(parse_state({}, n)),
                     self.session.render(parse_state({"azimuth": 15.0}, n))))

    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "cache"))
    monkeypatch.setattr(ViewerServer, "serve_forever", two_renders)
    assert main(["view", "--run", str(run), "--resolution", "16", "--test-views", "1"]) == 0
    out = capsys.readouterr().out
    assert "controlgs view: builtin-ar, methods no_ss, ss, controlgs on cpu" in out
    (session, dataset, orbit), = seen
    assert len(session.cameras) == 1 and session.info()["name"] == "builtin-ar"
    assert dataset["size"] == [16, 16] and orbit["size"] == [16, 16]
    assert dataset["has_truth"] and orbit["has_truth"]  # the built-in scene: ray-cast truth of any camera
    psnr = {m["name"] if "name" in m else i: m["metrics"]["psnr"] for i, m in enumerate(orbit["methods"])}
    assert all(v is not None and v > 5 for v in psnr.values()), orbit["methods"]


@needs_backbone
def test_view_of_a_user_scene(tmp_path: Any, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]) -> None:
    """``controlgs view --run RUN`` on a COLMAP capture of non-square views and the built-in backbone's
    Scaffold-GS folder (model and data from RUN/run.json); the server's loop is replaced by two renders."""

    from controlgs_adapter.cli import main
    from controlgs_adapter.scene import load_builtin_scene
    scene = load_builtin_scene("ar", 32, views=8, test_every=8, samples=1)
    cams, images = [], []
    for c, img in zip(scene.test_cameras + scene.train_cameras, torch.cat([scene.test_images, scene.train_images])):
        k = c.intrinsics.clone()
        k[1, 2] -= 4
        cams.append(Camera(c.world_to_camera, k, 32, 24))
        images.append(img[:, 4:28].contiguous())
    data, run, model_dir = write_colmap(tmp_path / "colmap", cams, images), tmp_path / "run", MODEL
    run.mkdir()
    random_adapter(load_model_dir(model_dir), run / "controlgs.controlgs.safetensors")
    (run / "run.json").write_text(json.dumps({"model": str(model_dir), "data": str(data), "resolution": 32}))
    seen: list[dict[str, Any]] = []

    def two_renders(self: ViewerServer, poll_interval: float = 0.5) -> None:
        seen.append(self.session.render(parse_state({"downsample": 2.0}, len(self.session.cameras))))
        seen.append(self.session.render(parse_state({"azimuth": 15.0}, len(self.session.cameras))))

    monkeypatch.setattr(ViewerServer, "serve_forever", two_renders)
    assert main(["view", "--run", str(run), "--threads", "1"]) == 0
    out = capsys.readouterr().out
    assert "serving on http://127.0.0.1:" in out and "methods no_ss, ss, controlgs" in out
    dataset, orbit = seen
    assert dataset["size"] == [32, 24] and dataset["has_truth"] and dataset["methods"][2]["metrics"]["psnr"] > 10
    assert decode_png(dataset["methods"][2]["eye"]).shape == (24, 32, 3)
    assert not orbit["has_truth"] and orbit["methods"][2]["metrics"] is None  # your data: no ground truth off the views
