"""Tests of ``controlgs_adapter.commands.common``, the pieces the commands share: ``read_run`` (every run.json field
checked, naming the file and the field), ``apply_run_defaults`` (a run's renderer only with the user's say),
``--model``/``--data``, ``--lens`` (a run's lens, checked before it is taken), ``parse_device``, ``check_out_path`` (creates nothing), ``--cache-mib``, the scene-check
line, loading a user's scene, and ``--renderer``/``--rasterizer`` (``load_renderer``, ``make_renderer``)."""

from __future__ import annotations

import argparse
import json
import os
import sys
import textwrap
from pathlib import Path
from typing import Any

import pytest
import torch
from helpers.cli_runs import MODEL, needs_backbone
from helpers.scene_writers import write_colmap

from controlgs_adapter.backends.models.reference_model import NeuralGaussianModel
from controlgs_adapter.commands.common import (
    RasterizerRenderer,
    anchor_positions,
    apply_run_defaults,
    cache_bytes,
    check_line,
    check_out_path,
    check_rasterizer_name,
    lens_record,
    load_lens_arg,
    load_renderer,
    load_user_scene,
    make_renderer,
    parse_device,
    read_run,
    render_record,
    user_scene,
)
from controlgs_adapter.errors import ControlGSError, FileWriteError, InputValueError
from controlgs_adapter.rendering.protocol import FunctionRenderer, render_view, renderer_for
from controlgs_adapter.rendering.rasterizers import _CHOICE
from controlgs_adapter.scene import load_builtin_scene

FULL = {"model": "/m", "data": "/d", "family": "scaffold_gs", "model_iteration": 30000, "allow_unquantized": False,
        "format": "colmap", "images": "images_4", "holdout": 8, "white_background": False, "resolution": 256,
        "effects": ["display", "lens"], "iterations": 1000, "seed": 0, "seeds": 2, "adapters": ["controlgs", "no_lens"],
        "rasterizer": "auto", "renderer": "/r/mine.py:render", "lens": "/l/mine_psf_bank.safetensors",
        "distributed": {"processes": 1, "backend": None, "exchange": "sparse"}}


def _write(folder: Path, record: Any) -> Path:
    (folder / "run.json").write_text(json.dumps(record))
    return folder / "run.json"


def _ns(**kw: Any) -> argparse.Namespace:
    return argparse.Namespace(**kw)


#: the options apply_run_defaults fills, unset
RUN_ARGS: dict[str, Any] = {"model": None, "data": None, "renderer": None, "rasterizer": None, "resolution": None}


#: a module whose ``renderer`` says which folder it was found in
_RENDERER_MODULE = textwrap.dedent('''
    class _R:
        origin = {origin!r}

        def visible(self, model, camera):
            return None

        def render(self, model, camera, visible, background):
            return None


    renderer = _R()
''')


#: a renderer that records the rasterizer chosen around each of its calls
_RENDERER_FILE = '''
from controlgs_adapter.rendering.rasterizers import _CHOICE

class Recorder:
    def __init__(self):
        self.seen = []

    def visible(self, model, camera):
        self.seen.append(("visible", _CHOICE.get()))
        return "VIS"

    def render(self, model, camera, visible, background):
        self.seen.append(("render", _CHOICE.get(), visible))
        return "IMG"

recorder = Recorder()
'''


# ----------------------------------------------------------------------------- run.json

def test_read_run_takes_a_full_record_and_nothing(tmp_path: Path) -> None:
    assert read_run(tmp_path) is None
    _write(tmp_path, FULL)
    assert read_run(tmp_path) == FULL
    _write(tmp_path, {k: None for k in FULL} | {"future_field": [1, {"x": 2}]})  # nulls and unknown fields pass
    assert read_run(tmp_path) is not None


@pytest.mark.parametrize("field, value", [
    ("model", ""), ("model", "a\0b"), ("data", ["d"]), ("family", "gsplat"), ("model_iteration", -1),
    ("allow_unquantized", 1), ("format", 3), ("images", {}), ("holdout", 2.5), ("white_background", "false"),
    ("resolution", True), ("effects", []), ("effects", "display"), ("effects", ["display", 1]), ("iterations", -5),
    ("seed", 2**63), ("seeds", 0), ("adapters", "controlgs"), ("rasterizer", 0), ("renderer", ["x.py:r"]),
    ("distributed", {"processes": [1]}), ("variant", "xr"), ("lens", ""), ("lens", 3), ("lens", ["cardboard"]),
])
def test_each_field_is_checked_naming_file_and_field(tmp_path: Path, field: str, value: Any) -> None:
    path = _write(tmp_path, {**FULL, field: value})
    with pytest.raises(InputValueError) as e:
        read_run(tmp_path)
    assert str(e.value).startswith(f"{path}: field {field!r} must be ") and "got " in str(e.value)


def test_a_run_file_that_is_not_a_json_object(tmp_path: Path) -> None:
    for text in ("[]", "5", "null", "\"x\"", "{", "\xff", "[" * 50_000 + "]" * 50_000):
        (tmp_path / "run.json").write_bytes(text.encode("utf-8", "surrogateescape") if text != "\xff" else b"\xff")
        with pytest.raises(InputValueError, match=f"{tmp_path / 'run.json'}: not a controlgs run file"):
            read_run(tmp_path)
    (tmp_path / "run.json").unlink()
    (tmp_path / "run.json").mkdir()
    with pytest.raises(InputValueError, match="not a file"):
        read_run(tmp_path)


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
    (tmp_path / "run.json").write_text('{"model": "m", "data": "d", "holdout": 4, "resolution": null, "seed": 3}')
    ns = _ns(model=None, data="mine", holdout=None, resolution=None)
    assert apply_run_defaults(ns, tmp_path) == {"model": "m", "data": "d", "holdout": 4, "resolution": None, "seed": 3}
    assert (ns.model, ns.data, ns.holdout, ns.resolution) == ("m", "mine", 4, None) and not hasattr(ns, "seed")
    (tmp_path / "run.json").write_text("{not json")
    with pytest.raises(InputValueError, match=f"{tmp_path / 'run.json'}: not a controlgs run file"):
        apply_run_defaults(_ns(model=None), tmp_path)


def test_a_run_renderer_needs_the_users_say(tmp_path: Path) -> None:
    spec = "/elsewhere/evil.py:renderer"
    _write(tmp_path, {"model": "/m", "data": "/d", "renderer": spec})
    args = _ns(**RUN_ARGS)
    with pytest.raises(InputValueError) as e:
        apply_run_defaults(args, tmp_path)
    assert f"--renderer {spec}" in str(e.value) and "--trust-run-renderer" in str(e.value)
    assert args.renderer is None
    args = _ns(**{**RUN_ARGS, "renderer": "mine:render"})  # named on the command line: the user's, not the run's
    assert apply_run_defaults(args, tmp_path) is not None and args.renderer == "mine:render"
    args = _ns(**RUN_ARGS, trust_run_renderer=True)
    assert apply_run_defaults(args, tmp_path) is not None
    assert (args.renderer, args.model, args.data) == (spec, "/m", "/d")


def test_a_runs_lens_is_taken_unless_given_and_a_missing_file_is_named(tmp_path: Path) -> None:
    bank = tmp_path / "mine_psf_bank.safetensors"
    bank.write_bytes(b"")  # only its existence is checked here
    _write(tmp_path, {"model": "/m", "data": "/d", "lens": str(bank)})
    args = _ns(**RUN_ARGS, lens=None)
    apply_run_defaults(args, tmp_path)
    assert args.lens == str(bank)
    args = _ns(**RUN_ARGS, lens="cardboard")  # named on the command line: kept
    apply_run_defaults(args, tmp_path)
    assert args.lens == "cardboard"
    for recorded, why in ((str(tmp_path / "gone.json"), "no such file"), ("cardbaord", "not a shipped lens"),
                          (str(tmp_path / "lens.txt"), "not a lens file")):
        (tmp_path / "lens.txt").write_text("{}")
        path = _write(tmp_path, {"model": "/m", "data": "/d", "lens": recorded})
        args = _ns(**RUN_ARGS, lens=None)
        with pytest.raises(InputValueError) as e:
            apply_run_defaults(args, tmp_path)
        assert str(e.value).startswith(f"{path}: field 'lens': ") and why in str(e.value) and "--lens" in str(e.value)
        assert args.lens is None and args.model is None  # nothing taken from a refused run file


def test_the_lens_option_loads_the_lens_and_records_a_file_by_its_absolute_path(tmp_path, monkeypatch) -> None:
    from helpers.banks import random_bank

    assert lens_record(load_lens_arg(_ns(lens=None))) == "cardboard"
    random_bank(C=5).save(tmp_path / "b.safetensors")
    monkeypatch.chdir(tmp_path)
    lens = load_lens_arg(_ns(lens="b.safetensors"))
    assert lens.spec == "b.safetensors" and lens_record(lens) == str(tmp_path / "b.safetensors")
    with pytest.raises(InputValueError, match="^--lens nope.json: no such file$"):
        load_lens_arg(_ns(lens="nope.json"))


# ----------------------------------------------------------------------------- options

def test_user_scene_needs_both_or_neither() -> None:
    assert user_scene(_ns(model=None, data=None)) is False
    assert user_scene(_ns(model="m", data="d")) is True
    for model, data in (("m", None), (None, "d")):
        with pytest.raises(InputValueError, match="--model.*--data"):
            user_scene(_ns(model=model, data=data))


def test_a_device_that_cannot_hold_data_is_refused_naming_it() -> None:
    assert parse_device("cpu") == torch.device("cpu") and str(parse_device("cpu")) == "cpu"
    for name in ("meta", "cuda:99", "nodevice", "xla", "gpu0"):
        with pytest.raises(InputValueError, match=f"^--device '?{name}'?: "):
            parse_device(name)
    if not torch.cuda.is_available():
        with pytest.raises(InputValueError, match="--device cuda:1: CUDA is not available"):
            parse_device("cuda:1")


def test_check_out_path_creates_nothing(tmp_path: Path) -> None:
    deep = tmp_path / "a" / "b" / "c"
    assert check_out_path(deep, "--out", folder=True) == deep
    assert check_out_path(deep / "f.json", "--out", folder=False) == deep / "f.json"
    assert list(tmp_path.iterdir()) == []
    (tmp_path / "file").write_text("")
    with pytest.raises(InputValueError, match=f"^--out {tmp_path / 'file'}: is a file"):
        check_out_path(tmp_path / "file", "--out", folder=True)
    with pytest.raises(InputValueError, match=f"^--bank {tmp_path}: is a folder"):
        check_out_path(tmp_path, "--bank", folder=False)
    with pytest.raises(ControlGSError, match=f"^--out {tmp_path / 'file' / 'x' / 'y'}: {tmp_path / 'file'} is a file"):
        check_out_path(tmp_path / "file" / "x" / "y", "--out", folder=True)


@pytest.mark.skipif(os.geteuid() == 0, reason="root may write anywhere")
def test_check_out_path_refuses_a_read_only_folder(tmp_path: Path) -> None:
    locked = tmp_path / "locked"
    locked.mkdir(mode=0o500)
    try:
        with pytest.raises(FileWriteError, match=f"^--out {locked / 'run'}: cannot write into {locked}"):
            check_out_path(locked / "run", "--out", folder=True)
    finally:
        locked.chmod(0o700)


def test_cache_bytes_is_mib_times_2_to_the_20() -> None:
    assert cache_bytes(_ns(cache_mib=3)) == 3 * 1024 * 1024
    assert cache_bytes(_ns(cache_mib=0)) == 0
    for bad in (-1, 1.5, "8"):
        with pytest.raises(InputValueError, match=rf"--cache-mib.*got {bad!r}$"):
            cache_bytes(_ns(cache_mib=bad))


# ----------------------------------------------------------------------------- the scene check and a user's scene

def test_check_line() -> None:
    report = {"format": "colmap", "source": "/d", "splits": {"train": 7, "test": 1}, "points": 12,
              "in_front": {"a": 0.9, "b": 0.1, "c": 0.5, "d": 0.7}, "blind": ["b"]}
    assert check_line(report) == ("scene check: colmap /d: 7 train, 1 test views, image sizes match their cameras; "
                                  "the model's 12 anchors are in view of 3/4 cameras (median 70% inside the image)")
    report.update(format=None, in_front={})
    assert check_line(report) == "scene check: dataset /d: 7 train, 1 test views, image sizes match their cameras"


@needs_backbone
def test_user_scene_defaults_every_8th_view_held_out(tmp_path: Path) -> None:
    model = MODEL
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


def test_anchor_positions_are_plain_cpu_values(tiny_adapter):
    model, _, _ = tiny_adapter
    pos = anchor_positions(model)
    assert pos.dtype == torch.float32 and pos.device.type == "cpu" and pos.shape[1] == 3
    assert not pos.requires_grad and pos.grad_fn is None  # no autograd graph back into the model
    assert anchor_positions(object()) is None  # no backend recognises it


# ----------------------------------------------------------------------------- --renderer and --rasterizer

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


def test_load_renderer_from_files_and_modules(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
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
    with pytest.raises(InputValueError, match="r.py has no attribute 'nope'"):
        load_renderer("r.py:nope")


def test_load_renderer_finds_the_current_folders_module_first_and_leaves_sys_path_as_it_was(tmp_path, monkeypatch):
    """``--renderer MODULE:ATTR`` looks in the current folder first, as ``python -m`` would: a module of
    the same name elsewhere on the path (even first on it) does not shadow it; and the lookup leaves
    ``sys.path`` as it found it, however often it runs."""
    name = "cgs_user_renderer_lookup"
    here, elsewhere = tmp_path / "here", tmp_path / "elsewhere"
    for folder in (here, elsewhere):
        folder.mkdir()
        (folder / f"{name}.py").write_text(_RENDERER_MODULE.format(origin=folder.name))
    monkeypatch.syspath_prepend(str(elsewhere))  # first on the path (monkeypatch restores sys.path)
    monkeypatch.chdir(here)
    monkeypatch.delitem(sys.modules, name, raising=False)
    before = list(sys.path)
    try:
        first = load_renderer(f"{name}:renderer")
        assert first.origin == "here"
        assert sys.path == before
        load_renderer(f"{name}:renderer")
        assert sys.path == before  # no growth on a second lookup
    finally:
        sys.modules.pop(name, None)


def test_load_renderer_refusals(tmp_path, monkeypatch):
    (tmp_path / "rr.py").write_text(
        "class K:\n    pass\n\nnumber = 3\n\ndef few(model):\n    return None\n\n"
        "class BadVisible:\n    def visible(self, model):\n        return None\n\n"
        "    def render(self, model, camera, visible, background):\n        return None\n\n"
        "bad_visible = BadVisible()\nbuiltin = max\n")
    f = tmp_path / "rr.py"
    for attr, message in (("K", "K is a class; name an instance of it or a function"),
                          ("number", r"number does not fit the render protocol \(a int\)"),
                          ("few", "few does not fit the render protocol"),
                          ("bad_visible", "bad_visible does not fit the render protocol")):
        with pytest.raises(InputValueError, match=message):
            load_renderer(f"{f}:{attr}")
    assert load_renderer(f"{f}:builtin") is not None  # no signature to inspect: accepted
    with pytest.raises(InputValueError, match=f"no such file {tmp_path / 'none.py'}"):
        load_renderer(f"{tmp_path / 'none.py'}:fn")
    for spec in ("nocolon", ":fn", "rr.py:1fn"):
        with pytest.raises(InputValueError, match="must be MODULE:ATTR"):
            load_renderer(spec)
    monkeypatch.chdir(tmp_path)
    with pytest.raises(InputValueError, match=r"no module named 'no_such_mod_xyz' .*path/to/file.py:fn\)"):
        load_renderer("no_such_mod_xyz:fn")
    with pytest.raises(InputValueError, match="no module named 'no_such_pkg_xyz'"):
        load_renderer("no_such_pkg_xyz.sub:fn")
    assert str(tmp_path) not in sys.path  # the current folder is taken off the path again
    r = RasterizerRenderer(load_renderer("rr:builtin"), "torch")
    assert repr(r).endswith(" with rasterizer 'torch'")


def test_make_renderer_wraps_the_chosen_rasterizer(tmp_path, tiny_adapter):
    """No option (or auto): the model's own renderer; ``--rasterizer torch`` renders the same image through the
    chosen rasterizer; a user's renderer is wrapped, the rasterizer chosen around its render only; an unknown or
    unusable rasterizer is refused naming it and what it needs."""
    built_in, views, _ = tiny_adapter
    model = NeuralGaussianModel(6, feat_dim=8, n_offsets=2)
    assert make_renderer(_ns(rasterizer=None, renderer=None), model) is None  # the model's own
    assert make_renderer(_ns(rasterizer="auto", renderer=None), model) is None
    plain = make_renderer(_ns(rasterizer="torch", renderer=None), model)
    assert isinstance(plain, RasterizerRenderer) and plain.rasterizer == "torch"
    assert type(plain.renderer) is type(renderer_for(model))
    r = make_renderer(_ns(rasterizer="torch", renderer=None), built_in)
    cam, _ = views[0]
    with torch.no_grad():
        assert torch.equal(render_view(None, built_in, cam, None, views.background, renderer=r),
                           render_view(None, built_in, cam, None, views.background))

    (tmp_path / "rec.py").write_text(_RENDERER_FILE)
    wrapped = make_renderer(_ns(rasterizer="torch", renderer=f"{tmp_path / 'rec.py'}:recorder"), model)
    assert isinstance(wrapped, RasterizerRenderer) and wrapped.rasterizer == "torch"
    assert wrapped.visible(model, None) == "VIS" and wrapped.render(model, None, "VIS", None) == "IMG"
    # the user's object itself is wrapped; the rasterizer is chosen around render only, for that call
    assert wrapped.renderer.seen == [("visible", None), ("render", "torch", "VIS")]
    assert _CHOICE.get() is None

    with pytest.raises(InputValueError, match=r"--rasterizer 'nope' is not registered; available: gsplat, torch, auto"):
        make_renderer(_ns(rasterizer="nope", renderer=None), model)
    with pytest.raises(InputValueError, match=r"^--rasterizer gsplat cannot render on cpu: .*--device cuda .*"
                                              r"pip install 'controlgs-adapter\[gsplat\]'"):
        make_renderer(_ns(rasterizer="gsplat", renderer=None), model)


@pytest.mark.parametrize("images", ["../../etc", "/abs/images", "images/../../x"])
def test_a_run_files_images_folder_stays_under_the_dataset(tmp_path: Path, images: str) -> None:
    path = _write(tmp_path, {**FULL, "images": images})
    with pytest.raises(InputValueError) as e:
        read_run(tmp_path)
    assert str(e.value).startswith(f"{path}: field 'images' must be a folder under the dataset")


def test_a_run_file_that_is_a_folder_is_named_once(tmp_path: Path) -> None:
    (tmp_path / "run.json").mkdir()
    with pytest.raises(InputValueError) as e:
        read_run(tmp_path)
    assert str(e.value) == f"{tmp_path / 'run.json'}: not a controlgs run file (not a file)"
