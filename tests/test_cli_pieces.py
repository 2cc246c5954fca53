"""The command line's pieces called directly (no training): option checks and their one-line errors,
``run.json`` defaults, ``--device`` / ``--cache-mib`` / ``--effects`` parsing, the scene-check line,
exit codes of ``controlgs``, the run-folder lock's holder record, and the viewer's state bounds."""

from __future__ import annotations

import argparse
import fcntl
import json
import os
from datetime import datetime
from pathlib import Path
from typing import Any

import pytest
import torch

from controlgs_adapter import cli
from controlgs_adapter.commands.adapters import effects_from
from controlgs_adapter.commands.common import (apply_run_defaults, cache_bytes, check_line, check_rasterizer_name,
                                               parse_device, render_record, user_scene)
from controlgs_adapter.errors import FileWriteError, InputValueError, RunLockedError
from controlgs_adapter.lock import lock_holder, run_lock
from controlgs_adapter.rendering.protocol import FunctionRenderer, as_renderer
from controlgs_adapter.viewer.session import ViewState, parse_state


def _ns(**kw: Any) -> argparse.Namespace:
    return argparse.Namespace(**kw)


# ---------------------------------------------------------------- --model / --data
def test_user_scene_needs_both_or_neither() -> None:
    assert user_scene(_ns(model=None, data=None)) is False
    assert user_scene(_ns(model="m", data="d")) is True
    for model, data in (("m", None), (None, "d")):
        with pytest.raises(InputValueError, match="give both --model MODEL_DIR and --data DATA_DIR"):
            user_scene(_ns(model=model, data=data))


# ---------------------------------------------------------------- run.json defaults
def test_run_defaults_fill_only_unset_listed_options(tmp_path: Path) -> None:
    assert apply_run_defaults(_ns(model=None), tmp_path) is None  # no run.json: nothing filled
    run = {"model": "/m", "data": "/d", "holdout": 4, "resolution": 32, "format": None, "iterations": 7,
           "rasterizer": "torch"}
    (tmp_path / "run.json").write_text(json.dumps(run))
    args = _ns(model=None, data="/mine", holdout=None, resolution=None, format="colmap", iterations=None, rasterizer=None)
    assert apply_run_defaults(args, tmp_path) == run
    assert (args.model, args.data, args.holdout, args.resolution) == ("/m", "/mine", 4, 32)
    assert args.format == "colmap"  # set by the user: kept; a null in run.json never overrides
    assert args.iterations is None  # not an eval option: run.json does not set it
    assert args.rasterizer == "torch"
    (tmp_path / "run.json").write_text("{not json")
    with pytest.raises(InputValueError, match=r"run\.json: not a controlgs run file"):
        apply_run_defaults(_ns(model=None), tmp_path)


# ---------------------------------------------------------------- --device, --cache-mib, --effects, --rasterizer
def test_parse_device() -> None:
    assert parse_device("cpu") == torch.device("cpu")
    with pytest.raises(InputValueError, match="--device 'gpu0'"):
        parse_device("gpu0")
    if not torch.cuda.is_available():
        with pytest.raises(InputValueError, match="--device cuda:1: CUDA is not available"):
            parse_device("cuda:1")


def test_cache_bytes_is_mib_times_2_to_the_20() -> None:
    assert cache_bytes(_ns(cache_mib=3)) == 3 * 1024 * 1024
    assert cache_bytes(_ns(cache_mib=0)) == 0
    for bad in (-1, 1.5, "8"):
        with pytest.raises(InputValueError, match=r"--cache-mib must be an int >= 0 \(MiB\), got"):
            cache_bytes(_ns(cache_mib=bad))


def test_effects_from_keeps_pipeline_order() -> None:
    from controlgs_adapter.training import DEFAULT_EFFECTS

    order = list(DEFAULT_EFFECTS)
    picked = [order[-1], order[0]]
    got = effects_from(f" {picked[0]} ,{picked[1]},")
    assert list(got) == [order[0], order[-1]] and all(v is True for v in got.values())
    assert effects_from(picked) == got
    assert effects_from(None) == dict(DEFAULT_EFFECTS)
    for bad in ("", " , ", f"{order[0]},bloom"):
        with pytest.raises(InputValueError, match="--effects must be a comma-separated list of"):
            effects_from(bad)


def test_rasterizer_names() -> None:
    for ok in (None, "auto", "torch"):
        check_rasterizer_name(ok)
    with pytest.raises(InputValueError, match=r"--rasterizer 'nope' is not registered; available: .*torch.*, auto"):
        check_rasterizer_name("nope")


def test_render_record(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.chdir(tmp_path)
    assert render_record(_ns(rasterizer=None, renderer=None)) == {"rasterizer": "auto", "renderer": None}
    assert render_record(_ns(rasterizer="torch", renderer="pkg.mod:fn")) == {"rasterizer": "torch", "renderer": "pkg.mod:fn"}
    rec = render_record(_ns(rasterizer=None, renderer="sub/r.py:fn"))
    assert rec["renderer"] == f"{tmp_path.resolve() / 'sub' / 'r.py'}:fn"


# ---------------------------------------------------------------- the scene-check line
def test_check_line_by_hand() -> None:
    report = {"format": "colmap", "source": "/d", "splits": {"train": 7, "test": 1}, "points": 12,
              "in_front": {"a": 0.9, "b": 0.1, "c": 0.5, "d": 0.7}, "blind": ["b"]}
    assert check_line(report) == ("scene check: colmap /d: 7 train, 1 test views, image sizes match their cameras; "
                                  "the model's 12 anchors are in view of 3/4 cameras (median 70% inside the image)")
    report.update(format=None, in_front={})
    assert check_line(report) == "scene check: dataset /d: 7 train, 1 test views, image sizes match their cameras"


# ---------------------------------------------------------------- exit codes
def test_cli_exit_codes(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert cli.main([]) == 0
    assert "usage: controlgs" in capsys.readouterr().out
    blocker = tmp_path / "file"
    blocker.write_text("")
    assert cli.main(["train", "--out", str(blocker / "run"), "--model", "m"]) == 2  # lock folder under a file
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("controlgs train: error: ") and str(blocker) in err[0]
    with pytest.raises(SystemExit) as e:
        cli.main(["train", "--device"])  # argparse's own usage error
    assert e.value.code == 2


# ---------------------------------------------------------------- run-folder lock
def test_lock_records_this_holder_and_clears_it(tmp_path: Path) -> None:
    with run_lock(tmp_path / "run") as path:
        assert path == tmp_path / "run" / ".lock"
        holder = lock_holder(tmp_path / "run")
        assert holder is not None and holder["pid"] == os.getpid()
        with pytest.raises(RunLockedError, match=f"pid {os.getpid()} on "):  # a second open file: refused
            run_lock(tmp_path / "run").__enter__()
    assert lock_holder(tmp_path / "run") is None  # released: the record is cleared
    assert lock_holder(tmp_path / "none") is None


def test_lock_message_of_a_foreign_or_unreadable_holder(tmp_path: Path) -> None:
    folder = tmp_path / "run"
    folder.mkdir()
    fd = os.open(folder / ".lock", os.O_RDWR | os.O_CREAT)
    try:
        fcntl.flock(fd, fcntl.LOCK_EX)
        os.write(fd, b"garbage")
        with pytest.raises(RunLockedError, match="its lock file is unreadable"):
            run_lock(folder).__enter__()
        t = 86400.0 * 365
        os.ftruncate(fd, 0)
        os.pwrite(fd, json.dumps({"pid": 4242, "host": "h", "time": t, "command": "c x"}).encode(), 0)
        with pytest.raises(RunLockedError) as e:
            run_lock(folder).__enter__()
        started = datetime.fromtimestamp(t).strftime("%Y-%m-%d %H:%M:%S")
        assert f"{folder}: this run folder is in use by pid 4242 on h since {started} (c x)" in str(e.value)
    finally:
        os.close(fd)
    (tmp_path / "f").write_text("")
    with pytest.raises(FileWriteError, match=str(tmp_path / "f")):
        run_lock(tmp_path / "f" / "run").__enter__()


# ---------------------------------------------------------------- render protocol pieces
def test_function_renderer_unwraps_results() -> None:
    img = torch.rand(3, 2, 2)

    class Out:
        color = img

    r = FunctionRenderer(lambda m, c, v, b: {"render": img, "viewspace_points": None})
    assert r.render(None, None, None, None) is img and r.visible(None, None) is None
    assert FunctionRenderer(lambda m, c, v, b: Out()).render(None, None, None, None) is img
    mask = torch.tensor([True, False])
    assert FunctionRenderer(lambda *a: img, visible=lambda m, c: mask).visible(None, None) is mask
    with pytest.raises(InputValueError, match="FunctionRenderer takes callables, got render=3"):
        FunctionRenderer(3)  # type: ignore[arg-type]
    fn = as_renderer(lambda m, c, v, b: img, None)
    assert isinstance(fn, FunctionRenderer) and fn.render(None, None, None, None) is img
    assert as_renderer(r, None) is r

    class HalfRenderer:  # has the two names, but visible is not callable: not a Renderer
        visible = None

        def render(self, *a: Any) -> Any:
            return img

    with pytest.raises(InputValueError, match="got HalfRenderer"):
        as_renderer(HalfRenderer(), None)


# ---------------------------------------------------------------- viewer state bounds
@pytest.mark.parametrize("field, lo, hi", [("downsample", 1.0, 8.0), ("power_saving", 0.0, 0.8),
                                           ("azimuth", -180.0, 180.0), ("elevation", -80.0, 80.0)])
def test_parse_state_bounds_are_inclusive(field: str, lo: float, hi: float) -> None:
    for v in (lo, hi):
        assert getattr(parse_state({field: v}, 1), field) == v
    for v in (lo - 1e-6, hi + 1e-6):
        with pytest.raises(InputValueError, match=field):
            parse_state({field: v}, 1)


def test_parse_state_view_gaze_and_json_round_trip() -> None:
    assert parse_state({"view": 2}, 3).view == 2
    with pytest.raises(InputValueError, match=r"view must be an integer in \[0, 2\]"):
        parse_state({"view": -1}, 3)
    for gaze in ([1, -1], [-1, 1]):
        assert parse_state({"gaze": gaze}, 1).gaze == tuple(float(g) for g in gaze)
    with pytest.raises(InputValueError, match="gaze y must be"):
        parse_state({"gaze": [0, 1.5]}, 1)
    with pytest.raises(InputValueError, match="gaze must be null"):
        parse_state({"gaze": [0, 0, 0]}, 1)
    s = parse_state({"view": 1, "azimuth": 10, "stages": ["optics", "lens"], "gaze": [0.25, 0.5]}, 2)
    js = s.to_json()
    assert js["stages"] == ["lens", "optics"] and js["gaze"] == [0.25, 0.5]
    assert parse_state(json.loads(json.dumps(js)), 2) == s
    assert ViewState().to_json()["gaze"] is None and not ViewState().orbit
    assert parse_state({"elevation": 5}, 1).orbit


# ---------------------------------------------------------------- defaults of a user scene
def test_user_scene_defaults_every_8th_view_held_out(tmp_path: Path) -> None:
    from _scene_writers import write_colmap
    from controlgs_adapter.commands.common import load_user_scene
    from controlgs_adapter.scene import builtin_backbone_dir, load_builtin_scene

    model = builtin_backbone_dir("ar")
    if not (model / "point_cloud").is_dir():
        pytest.skip("built-in backbone not baked")
    scene = load_builtin_scene("ar", 16, views=9, test_every=9, samples=1)
    cams = scene.test_cameras + scene.train_cameras
    write_colmap(tmp_path / "data", cams, list(torch.cat([scene.test_images, scene.train_images])))
    args = _ns(model=str(model), data=str(tmp_path / "data"), family=None, model_iteration=None, allow_unquantized=None,
               format=None, images=None, holdout=None, white_background=None, resolution=None, device="cpu")
    user = load_user_scene(args)
    assert [f.name for f in user.data.splits["test"]] == ["v00.png", "v08.png"]  # 9 views, every 8th: 0 and 8
    assert len(user.data.splits["train"]) == 7 and user.family == "scaffold_gs"
    rec = user.record(args, iterations=3)
    assert rec["holdout"] == 8 and rec["model"] == str(model.resolve()) and rec["data"] == str((tmp_path / "data").resolve())
    assert (rec["allow_unquantized"], rec["white_background"], rec["format"], rec["iterations"]) == (False, False, "colmap", 3)


def test_eval_seed_folders(tmp_path: Path) -> None:
    from controlgs_adapter.commands.eval import seed_folders

    assert seed_folders(tmp_path, 5, None) == [(5, tmp_path)]  # no seed folders: the run folder itself
    for name in ("seed-2", "seed--1", "seed-10", "seed-x", "seed-"):
        (tmp_path / name).mkdir()
    (tmp_path / "seed-7").write_text("")  # a file, not a folder
    assert seed_folders(tmp_path, 0, None) == [(-1, tmp_path / "seed--1"), (2, tmp_path / "seed-2"),
                                               (10, tmp_path / "seed-10")]
    assert seed_folders(tmp_path, 2, 1) == [(2, tmp_path)]
    assert seed_folders(tmp_path, -1, 2) == [(-1, tmp_path / "seed--1"), (0, tmp_path / "seed-0")]


def test_cli_error_with_a_newline_is_one_line(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """torch's message repeats the raw device string: the CLI still prints one line."""
    assert cli.main(["train", "--model", "m", "--data", "d", "--out", str(tmp_path / "r"), "--device", "cu\nda"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("controlgs train: error: --device 'cu\\nda': "), err


def _eval_run(tmp_path: Path, seeds: dict[str, tuple[str, ...]]) -> Path:
    run = tmp_path / "run"
    for folder, names in seeds.items():
        (run / folder).mkdir(parents=True, exist_ok=True)
        for n in names:
            (run / folder / f"{n}.controlgs.safetensors").write_text("")  # checked for presence before any load
    return run


@pytest.mark.parametrize("argv, message", [
    (["view", "--threads", "0"], "--threads must be an integer in [1, "),
    (["view", "--model", "m", "--data", "d"], "--model/--data need --run RUN"),
    (["view", "--rasterizer", "nope"], "--rasterizer 'nope' is not registered"),
    (["optics", "fit-prewarp", "--size", "9", "--out", "{d}/lut.safetensors"], "--size must be an even integer >= 8, got 9"),
    (["optics", "fit-prewarp", "--size", "6", "--out", "{d}/lut.safetensors"], "--size must be an even integer >= 8, got 6"),
    (["optics", "fit-prewarp", "--out", "{d}"], "--out {d}: is a folder"),
    (["optics", "build-bank", "--out", "{d}"], "--out {d}: is a folder"),
    (["optics", "build-bank", "--prescription", "{d}/big.json", "--out", "{d}/b.safetensors"], "big.json: 1048577 bytes, too large"),
    (["optics", "bench", "--sizes", "256", "1x4"], "--sizes: size must be N or HxW with N, H, W >= 2, got '1x4'"),
    (["eval", "--run", "{d}/run"], "seed-2: no controlgs.controlgs.safetensors"),
])
def test_command_refusals_are_one_line(tmp_path: Path, capsys: pytest.CaptureFixture[str], argv: list[str],
                                       message: str) -> None:
    (tmp_path / "big.json").write_bytes(b" " * ((1 << 20) + 1))
    _eval_run(tmp_path, {"seed-1": ("controlgs",), "seed-2": ("wo_lens",)})
    d = str(tmp_path)
    assert cli.main([a.replace("{d}", d) for a in argv]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith(f"controlgs {argv[0]}: error: ") and message.replace("{d}", d) in err[0], err


def test_eval_refuses_seed_folders_with_different_adapters(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    run = _eval_run(tmp_path, {"seed-1": ("controlgs",), "seed-2": ("controlgs", "wo_lens")})
    assert cli.main(["eval", "--run", str(run)]) == 2
    assert (f"{run}: the seed folders hold different adapters (seed-1: controlgs; seed-2: controlgs, wo_lens)"
            in capsys.readouterr().err)
    run = _eval_run(tmp_path / "one", {".": ()})
    assert cli.main(["eval", "--run", str(run)]) == 2  # one seed: the run folder itself is named
    assert f"controlgs eval: error: {run}: no controlgs.controlgs.safetensors" in capsys.readouterr().err


def test_load_renderer_from_files_and_modules(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    from controlgs_adapter.commands.common import load_renderer

    (tmp_path / "r.py").write_text(
        "def fn(model, camera, visible, background):\n    return 'image'\n\n"
        "class Obj:\n    def visible(self, model, camera):\n        return 'mask'\n\n"
        "    def render(self, model, camera, visible, background):\n        return 'obj image'\n\nobj = Obj()\n")
    (tmp_path / "inner_fail.py").write_text("import xyz_missing_pkg_for_test\n")
    r = load_renderer(f"{tmp_path / 'r.py'}:fn")
    assert isinstance(r, FunctionRenderer) and r.render(None, None, None, None) == "image" and r.visible(None, None) is None
    o = load_renderer(f"{tmp_path / 'r.py'}:obj")
    assert (o.visible(None, None), o.render(None, None, None, None)) == ("mask", "obj image")
    monkeypatch.chdir(tmp_path)
    assert load_renderer("r:obj").render(None, None, None, None) == "obj image"  # a module of the current folder
    with pytest.raises(ModuleNotFoundError) as e:  # a module the renderer's module imports: not hidden
        load_renderer("inner_fail:render")
    assert e.value.name == "xyz_missing_pkg_for_test"
    for spec, message in ((":fn", "must be MODULE:ATTR"), ("r.py:1fn", "must be MODULE:ATTR"),
                          ("r.py:nope", "r.py has no attribute 'nope'")):
        with pytest.raises(InputValueError, match=message):
            load_renderer(spec)
