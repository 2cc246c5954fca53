"""Bad-input catalogue (issue 12): every error a user can cause through the API, the files or the
CLI is one of the library's error types (or a one-line CLI error with exit code 2, no traceback)
whose message names the argument or file. Plus the run-folder lock across processes, file modes
and the clean-up of partial ``.tmp`` files."""

from __future__ import annotations

import json
import math
import os
import subprocess
import sys
import time
import types
from pathlib import Path
from typing import Any, Callable

import pytest
import torch

from controlgs_adapter import cli
from controlgs_adapter.formats.backbone import read_yaml_scalars
from controlgs_adapter.formats.backbone import load_state_dict_file, parse_cfg_args, read_cfg_args, read_ply
from controlgs_adapter.controlgs import ADAPTER_KIND, ControlGS
from controlgs_adapter.downstream.optics.bank import BANK_KIND, PSFBank
from controlgs_adapter.downstream.optics.generate import build_bank
from controlgs_adapter.downstream.optics.prescription import CARDBOARD, Prescription
from controlgs_adapter.errors import (ControlGSError, FileFormatError, FileWriteError, InputValueError,
                                      NonFiniteError, RunLockedError, ShapeError, StateError)
from controlgs_adapter.formats.safetensors import atomic_write, file_mode, load_tensors, read_header, save_tensors
from controlgs_adapter.lock import run_lock
from controlgs_adapter.losses import LossWeights
from controlgs_adapter.state import Camera, RuntimeState
from controlgs_adapter.training import TrainConfig

from _rawfiles import write_raw
from scaffold_standin import ScaffoldStandIn, make_camera
from test_optics_bank import tiny_bank

ROOT = Path(__file__).resolve().parents[1]


def _raises(fn: Callable[[], Any], error: type[BaseException] | tuple[type[BaseException], ...], *names: str) -> str:
    """Call ``fn``; it must raise ``error`` (a ControlGSError) whose message holds every one of ``names``."""
    with pytest.raises(error) as info:
        fn()
    assert isinstance(info.value, ControlGSError), type(info.value)
    msg = str(info.value)
    for n in names:
        assert n in msg, f"{n!r} not in {msg!r}"
    return msg


# ============================================================================ API: run-time state, camera
EYE4, K = torch.eye(4), torch.tensor([[50.0, 0.0, 32.0], [0.0, 50.0, 24.0], [0.0, 0.0, 1.0]])


def _k(**cells: float) -> torch.Tensor:
    k = K.clone()
    for key, v in cells.items():
        k[int(key[1]), int(key[2])] = v
    return k


def _w2c(fn: Callable[[torch.Tensor], None]) -> torch.Tensor:
    m = EYE4.clone()
    fn(m)
    return m


STATE_CASES = [
    ({"downsample": None}, "downsample"), ({"downsample": "abc"}, "downsample"), ({"downsample": "4"}, "downsample"),
    ({"downsample": math.nan}, "downsample"), ({"downsample": math.inf}, "downsample"), ({"downsample": 0.5}, "downsample"),
    ({"downsample": True}, "downsample"), ({"downsample": [2]}, "downsample"), ({"downsample": 1j}, "downsample"),
    ({"power_saving": -0.1}, "power_saving"), ({"power_saving": 1.0}, "power_saving"), ({"power_saving": None}, "power_saving"),
    ({"power_saving": math.nan}, "power_saving"), ({"power_saving": "0.2"}, "power_saving"),
    ({"gaze": 5}, "gaze"), ({"gaze": "ab"}, "gaze"), ({"gaze": (0.0,)}, "gaze"), ({"gaze": (0.0, 0.0, 0.0)}, "gaze"),
    ({"gaze": (2.0, 0.0)}, "gaze"), ({"gaze": (math.nan, 0.0)}, "gaze"), ({"gaze": ("a", 0.0)}, "gaze"),
    ({"gaze": (None, 0.0)}, "gaze"), ({"gaze": {"x": 0}}, "gaze"),
]


@pytest.mark.parametrize("kw, name", STATE_CASES, ids=[f"{k}={v!r}" for (kw, _) in STATE_CASES for k, v in kw.items()])
def test_runtime_state(kw, name):
    _raises(lambda: RuntimeState(**kw), StateError, name)


CAMERA_CASES = [
    ("width='abc'", {"width": "abc"}, "width"), ("width=0", {"width": 0}, "width"), ("width=-3", {"width": -3}, "width"),
    ("width=1.5", {"width": 1.5}, "width"), ("width=None", {"width": None}, "width"), ("width=True", {"width": True}, "width"),
    ("height='x'", {"height": "x"}, "height"), ("height=0", {"height": 0}, "height"),
    ("K zeros", {"intrinsics": torch.zeros(3, 3)}, "intrinsics"), ("K22=0", {"intrinsics": _k(k22=0.0)}, "intrinsics"),
    ("K22=2", {"intrinsics": _k(k22=2.0)}, "intrinsics"), ("fx<0", {"intrinsics": _k(k00=-50.0)}, "intrinsics"),
    ("fy=0", {"intrinsics": _k(k11=0.0)}, "intrinsics"), ("K20!=0", {"intrinsics": _k(k20=0.5)}, "intrinsics"),
    ("K nan", {"intrinsics": _k(k02=math.nan)}, "intrinsics"), ("K 3x4", {"intrinsics": torch.zeros(3, 4)}, "intrinsics"),
    ("K list", {"intrinsics": K.tolist()}, "intrinsics"), ("K int", {"intrinsics": K.long()}, "intrinsics"),
    ("w2c zeros", {"world_to_camera": torch.zeros(4, 4)}, "world_to_camera"),
    ("w2c scaled", {"world_to_camera": _w2c(lambda m: m[:3, :3].mul_(2.0))}, "world_to_camera"),
    ("w2c mirrored", {"world_to_camera": _w2c(lambda m: m[0, 0].fill_(-1.0))}, "world_to_camera"),
    ("w2c last row", {"world_to_camera": _w2c(lambda m: m[3, 0].fill_(1.0))}, "world_to_camera"),
    ("w2c sheared", {"world_to_camera": _w2c(lambda m: m[0, 1].fill_(0.3))}, "world_to_camera"),
    ("w2c nan", {"world_to_camera": _w2c(lambda m: m[0, 3].fill_(math.nan))}, "world_to_camera"),
    ("w2c 3x4", {"world_to_camera": torch.eye(3, 4)}, "world_to_camera"),
    ("w2c None", {"world_to_camera": None}, "world_to_camera"),
]


@pytest.mark.parametrize("kw, name", [c[1:] for c in CAMERA_CASES], ids=[c[0] for c in CAMERA_CASES])
def test_camera(kw, name):
    args = {"world_to_camera": EYE4, "intrinsics": K, "width": 64, "height": 48, **kw}
    _raises(lambda: Camera(**args), (InputValueError, ShapeError), name)


@pytest.mark.parametrize("fov", [0.0, math.pi, -0.5, math.nan, "wide"])
def test_scaffold_camera_fov(fov):
    vc = types.SimpleNamespace(world_view_transform=torch.eye(4), image_width=64, image_height=48, FoVx=fov, FoVy=0.8)
    _raises(lambda: Camera.from_scaffold(vc), InputValueError, "FoVx")


# ============================================================================ API: training configuration
CONFIG_CASES = [
    ("lr", math.inf), ("lr", math.nan), ("lr", 0.0), ("lr", -1e-3), ("lr", "fast"), ("lr", None),
    ("iterations", -1), ("iterations", 1.5), ("iterations", "10"), ("iterations", True),
    ("cond_dim", 0), ("cond_dim", 8.0), ("max_downsample", 0.5), ("max_downsample", math.inf),
    ("max_power_saving", 1.0), ("max_power_saving", -0.1), ("psf_fraction", 2.0), ("psf_fraction", math.nan),
    ("psf_mode", "slow"), ("batch_size", 0), ("checkpoint_every", -1), ("seed", -1), ("seed", 2.5),
    ("state_blind", "yes"), ("loss", {"l1": 1.0}), ("modules", [1, 2]), ("modules", 7),
]


@pytest.mark.parametrize("name, value", CONFIG_CASES, ids=[f"{n}={v!r}" for n, v in CONFIG_CASES])
def test_train_config(name, value):
    _raises(lambda: TrainConfig(**{name: value}), InputValueError, name)


def test_train_config_takes_one_module_name_as_one_module():
    assert TrainConfig(modules="lens").modules == ("lens",)


LOSS_CASES = [("l1", math.inf), ("l1", math.nan), ("l1", -1.0), ("l1", "a"), ("l1", None), ("ssim", math.inf),
              ("mse", math.inf), ("mse", True), ("lpips", 1.0)]


@pytest.mark.parametrize("name, value", LOSS_CASES, ids=[f"{n}={v!r}" for n, v in LOSS_CASES])
def test_loss_weights(name, value):
    _raises(lambda: LossWeights(**{name: value}), InputValueError, "lpips" if name == "lpips" else name)


# ============================================================================ API: adapter wrap / save / load
@pytest.fixture
def cgs():
    c = ControlGS.wrap(ScaffoldStandIn(30, seed=0))
    yield c
    if c._wrapped:
        c.unwrap()


def _nan_conditions(c: ControlGS) -> None:
    with torch.no_grad():
        c.injector.conditions[0, 0, 0] = math.nan


def _huge_conditions(c: ControlGS) -> None:
    with torch.no_grad():
        c.injector.conditions[0, 0, 0] = 1e6


ADAPTER_CASES = [
    ("save None", lambda c, d: c.save(None), InputValueError, "path"),
    ("save 123", lambda c, d: c.save(123), InputValueError, "path"),
    ("save onto a folder", lambda c, d: c.save(d), InputValueError, "is a folder"),
    ("save under a file", lambda c, d: c.save(d / "f.txt" / "a.safetensors"), FileWriteError, "f.txt"),
    ("save dtype", lambda c, d: c.save(d / "a.safetensors", dtype=torch.int8), InputValueError, "dtype"),
    ("save NaN", lambda c, d: (_nan_conditions(c), c.save(d / "a.safetensors")), NonFiniteError, "conditions"),
    ("save fp16 overflow", lambda c, d: (_huge_conditions(c), c.save(d / "a.safetensors", dtype=torch.float16)),
     NonFiniteError, "float16"),
    ("load None", lambda c, d: ControlGS.load(None, ScaffoldStandIn(30, seed=0)), InputValueError, "path"),
    ("load a folder", lambda c, d: ControlGS.load(d, ScaffoldStandIn(30, seed=0)), FileFormatError, "no such file"),
    ("load missing", lambda c, d: ControlGS.load(d / "none.safetensors", ScaffoldStandIn(30, seed=0)), FileFormatError,
     "none.safetensors"),
    ("conditioned modules=5", lambda c, d: c.conditioned(RuntimeState(), modules=5).__enter__(), InputValueError, "modules"),
    ("conditioned modules=['nope']", lambda c, d: c.conditioned(RuntimeState(), modules=["nope"]).__enter__(),
     InputValueError, "nope"),
    ("conditioned modules='lns'", lambda c, d: c.conditioned(RuntimeState(), modules="lns").__enter__(),
     InputValueError, "lns"),
    ("conditioned state=None", lambda c, d: c.conditioned(None).__enter__(), InputValueError, "state"),
    ("wrap modules='lens'", lambda c, d: ControlGS.wrap(ScaffoldStandIn(30, seed=1), modules="lens"), InputValueError,
     "modules"),
]


@pytest.mark.parametrize("call, error, name", [c[1:] for c in ADAPTER_CASES], ids=[c[0] for c in ADAPTER_CASES])
def test_adapter(cgs, tmp_path, call, error, name):
    (tmp_path / "f.txt").write_text("x")
    _raises(lambda: call(cgs, tmp_path), error, name)


def test_conditioned_takes_one_module_name_as_one_module(cgs):
    # "display" is one module, not the letters d, i, s, ...; nothing renders here, so the block warns
    with pytest.warns(RuntimeWarning, match="no wrapped decoder ran inside this conditioned block"):
        with cgs.conditioned(RuntimeState(power_saving=0.4), camera=make_camera(), modules="display"):
            assert list(cgs.injector._ctx.strengths) == ["display"]


# ============================================================================ API: safetensors I/O
IO_CASES = [
    ("NaN", {"w": torch.tensor([1.0, math.nan])}, NonFiniteError, "'w'"),
    ("Inf", {"w": torch.tensor([math.inf])}, NonFiniteError, "'w'"),
    ("fp16 inf", {"h": torch.tensor([1e5]).half()}, NonFiniteError, "float16"),
    ("not a tensor", {"w": [1.0, 2.0]}, InputValueError, "'w'"),
]


@pytest.mark.parametrize("tensors, error, name", [c[1:] for c in IO_CASES], ids=[c[0] for c in IO_CASES])
def test_save_tensors(tmp_path, tensors, error, name):
    _raises(lambda: save_tensors(tmp_path / "x.safetensors", tensors, {}, kind="k", format_version=1), error, name,
            "x.safetensors")
    assert not list(tmp_path.iterdir()), "nothing may be written"


def test_save_tensors_refuses_nan_in_the_header(tmp_path):
    _raises(lambda: save_tensors(tmp_path / "x.safetensors", {}, {"a": math.nan}, kind="k", format_version=1),
            NonFiniteError, "x.safetensors")


@pytest.mark.parametrize("path", [None, 3.5, ""], ids=["None", "float", "empty"])
def test_io_paths(path):
    _raises(lambda: save_tensors(path, {}, {}, kind="k", format_version=1), InputValueError, "path")
    _raises(lambda: read_header(path, kind="k", max_version=1), InputValueError, "path")


def test_atomic_write_onto_a_folder(tmp_path):
    _raises(lambda: atomic_write(tmp_path, lambda p: None), InputValueError, str(tmp_path))


HEADER_CASES = [
    ("format_version true", {"format_version": True}, "format_version"),
    ("format_version '1'", {"format_version": "1"}, "format_version"),
    ("format_version 0", {"format_version": 0}, "format_version"),
    ("format_version 1.0", {"format_version": 1.0}, "format_version"),
    ("format_version 99", {"format_version": 99}, "format_version"),
    ("header a list", {"raw_header": "[1, 2]"}, "JSON object"),
    ("header not JSON", {"raw_header": "{oops"}, "corrupt"),
    ("header deep JSON", {"raw_header": "[" * 100000 + "]" * 100000}, "corrupt"),
    ("other kind", {"kind": "psf_bank"}, "psf_bank"),
]


@pytest.mark.parametrize("kw, name", [c[1:] for c in HEADER_CASES], ids=[c[0] for c in HEADER_CASES])
def test_file_headers(tmp_path, kw, name):
    p = write_raw(tmp_path / "f.safetensors", {"w": torch.zeros(2)}, {}, **{"kind": ADAPTER_KIND, **kw})
    _raises(lambda: load_tensors(p, kind=ADAPTER_KIND, max_version=1), FileFormatError, "f.safetensors", name)


# ============================================================================ files: PSF banks
def _bank_file(tmp_path: Path, header: dict[str, Any] | None = None, drop: tuple[str, ...] = (), **tensors: Any) -> Path:
    b = tiny_bank()
    t = {"psf": b.psf.half(), "psf_pitch_mm": b.psf_pitch_mm, "field_x": b.field_x, "field_y": b.field_y,
         "chief": b.chief, "chief_x": b.chief_x, "chief_y": b.chief_y, **tensors}
    for k in drop:
        t.pop(k)
    h = {"wavelengths_nm": [656, 550, 486], "display_mm": [24, 24], **(header or {})}
    h = {k: v for k, v in h.items() if v is not None}
    return write_raw(tmp_path / "bank.safetensors", t, h, kind=BANK_KIND)


BANK_CASES = [
    ("display_mm '66'", {"header": {"display_mm": "66"}}, "display_mm"),
    ("display_mm [24]", {"header": {"display_mm": [24]}}, "display_mm"),
    ("display_mm [0, 24]", {"header": {"display_mm": [0, 24]}}, "display_mm"),
    ("display_mm [true, 24]", {"header": {"display_mm": [True, 24]}}, "display_mm"),
    ("display_mm ['24', '24']", {"header": {"display_mm": ["24", "24"]}}, "display_mm"),
    ("no wavelengths_nm", {"header": {"wavelengths_nm": None}}, "wavelengths_nm"),
    ("wavelengths_nm '656'", {"header": {"wavelengths_nm": "656"}}, "wavelengths_nm"),
    ("wavelengths_nm []", {"header": {"wavelengths_nm": []}}, "wavelengths_nm"),
    ("wavelengths_nm [-1, ...]", {"header": {"wavelengths_nm": [-1, 550, 486]}}, "wavelengths_nm"),
    ("meta a list", {"header": {"meta": [1]}}, "meta"),
    ("empty grid", {"psf": torch.zeros(3, 0, 0, 5, 5), "psf_pitch_mm": torch.zeros(3, 0, 0),
                    "field_x": torch.zeros(0), "field_y": torch.zeros(0)}, "empty grid"),
    ("no psf tensor", {"drop": ("psf",)}, "psf"),
    ("NaN pitch", {"psf_pitch_mm": torch.full((3, 3, 3), math.nan)}, "psf_pitch_mm"),
    ("psf even K", {"psf": torch.full((3, 3, 3, 4, 4), 1 / 16)}, "psf"),
]


@pytest.mark.parametrize("kw, name", [c[1:] for c in BANK_CASES], ids=[c[0] for c in BANK_CASES])
def test_psf_bank_files(tmp_path, kw, name):
    p = _bank_file(tmp_path, **kw)
    _raises(lambda: PSFBank.load(p), FileFormatError, "bank.safetensors", name)


@pytest.mark.parametrize("version", [True, "1", 0, None], ids=repr)
def test_psf_bank_format_version(tmp_path, version):
    b = tiny_bank()
    p = write_raw(tmp_path / "bank.safetensors", {"psf": b.psf}, {"wavelengths_nm": [656, 550, 486]}, kind=BANK_KIND,
                  format_version=version)
    _raises(lambda: PSFBank.load(p), FileFormatError, "bank.safetensors", "format_version")


BUILD_CASES = [
    ("psf_size=4", {"psf_size": 4}, "psf_size"), ("psf_size=3", {"psf_size": 3}, "psf_size"),
    ("psf_size='33'", {"psf_size": "33"}, "psf_size"), ("grid=(0, 0)", {"grid": (0, 0)}, "grid"),
    ("grid=(3,)", {"grid": (3,)}, "grid"), ("grid=(3, -1)", {"grid": (3, -1)}, "grid"),
    ("pupil_samples=1", {"pupil_samples": 1}, "pupil_samples"), ("min_pitch_px=0", {"min_pitch_px": 0.0}, "min_pitch_px"),
    ("min_pitch_px=nan", {"min_pitch_px": math.nan}, "min_pitch_px"), ("chief_grid=(1, 1)", {"chief_grid": (1, 1)}, "chief_grid"),
]


@pytest.mark.parametrize("kw, name", [c[1:] for c in BUILD_CASES], ids=[c[0] for c in BUILD_CASES])
def test_build_bank_arguments(kw, name):
    _raises(lambda: build_bank(**kw), InputValueError, name)


PRESCRIPTION_CASES = [
    ("a list", [1, 2], "mapping"), ("display_mm '66'", {**CARDBOARD, "display_mm": "66"}, "display_mm"),
    ("wavelengths '656'", {**CARDBOARD, "wavelengths_nm": "656"}, "wavelengths_nm"),
    ("surfaces [1]", {**CARDBOARD, "surfaces": [1]}, "surfaces[0]"),
    ("surfaces {}", {**CARDBOARD, "surfaces": {}}, "surfaces"),
    ("radius 'abc'", {**CARDBOARD, "surfaces": [{**CARDBOARD["surfaces"][0], "radius_mm": "abc"}, CARDBOARD["surfaces"][1]]},
     "radius_mm"),
    ("pupil true", {**CARDBOARD, "pupil_diameter_mm": True}, "pupil_diameter_mm"),
    ("no object distance", {k: v for k, v in CARDBOARD.items() if k != "object_distance_mm"}, "object_distance_mm"),
]


@pytest.mark.parametrize("spec, name", [c[1:] for c in PRESCRIPTION_CASES], ids=[c[0] for c in PRESCRIPTION_CASES])
def test_prescription(spec, name):
    _raises(lambda: Prescription(spec), InputValueError, name)


# ============================================================================ files: PLY, cfg_args, state dicts
HEAD = b"ply\nformat binary_little_endian 1.0\n"
PLY_CASES = [
    ("not ply", b"plx\n", "first line"),
    ("no end_header", HEAD + b"element vertex 1\nproperty float x\n", "end_header"),
    ("ascii 10M vertices in 84 bytes", b"ply\nformat ascii 1.0\nelement vertex 10000000\nproperty float x\n"
                                       b"property float y\nend_header\n1 2\n", "10000000 vertices"),
    ("binary 1e11 vertices", HEAD + b"element vertex 100000000000\nproperty float x\nend_header\n\0\0\0\0",
     "100000000000 vertices"),
    ("count 'abc'", HEAD + b"element vertex abc\nproperty float x\nend_header\n", "line 3"),
    ("count -5", HEAD + b"element vertex -5\nproperty float x\nend_header\n", "line 3"),
    ("count 1e3", HEAD + b"element vertex 1e3\nproperty float x\nend_header\n", "line 3"),
    ("count missing", HEAD + b"element vertex\nproperty float x\nend_header\n", "line 3"),
    ("unknown type", HEAD + b"element vertex 1\nproperty float128 x\nend_header\n", "float128"),
    ("property 2 words", HEAD + b"element vertex 1\nproperty float\nend_header\n", "line 4"),
    ("property 4 words", HEAD + b"element vertex 1\nproperty float x y\nend_header\n", "line 4"),
    ("list in vertex", HEAD + b"element vertex 1\nproperty list uchar int idx\nend_header\n", "list property"),
    ("format bogus", b"ply\nformat binary_middle_endian 1.0\nelement vertex 0\nend_header\n", "line 2"),
    ("format 2 words", b"ply\nformat ascii\nelement vertex 0\nend_header\n", "line 2"),
    ("no format", b"ply\nelement vertex 1\nproperty float x\nend_header\n\0\0\0\0", "'format'"),
    ("no vertex", HEAD + b"end_header\n", "'vertex'"),
    ("face before vertex", HEAD + b"element face 1\nproperty list uchar int i\nelement vertex 1\nend_header\n", "precedes"),
    ("property before element", HEAD + b"property float x\nelement vertex 1\nend_header\n", "line 3"),
    ("duplicate property", HEAD + b"element vertex 1\nproperty float x\nproperty float x\nend_header\n", "twice"),
    ("two vertex elements", HEAD + b"element vertex 1\nproperty float x\nelement vertex 1\nend_header\n", "second"),
    ("unknown keyword", HEAD + b"elemnt vertex 1\nend_header\n", "elemnt"),
    ("vertex without properties", HEAD + b"element vertex 5\nend_header\n", "no properties"),
    ("ascii not a number", b"ply\nformat ascii 1.0\nelement vertex 1\nproperty float x\nend_header\nabc\n", "not a number"),
    ("ascii short row", b"ply\nformat ascii 1.0\nelement vertex 2\nproperty float x\nproperty float y\nend_header\n"
                        b"1 2\n3\n", "vertex 1"),
    ("binary truncated", HEAD + b"element vertex 4\nproperty float x\nend_header\n" + b"\0" * 10, "truncated"),
    ("header of 2 MB", b"ply\n" + b"comment " + b"x" * (2 << 20) + b"\n", "header"),
]


@pytest.mark.parametrize("data, name", [c[1:] for c in PLY_CASES], ids=[c[0] for c in PLY_CASES])
def test_ply(tmp_path, data, name):
    p = tmp_path / "cloud.ply"
    p.write_bytes(data)
    t = time.perf_counter()
    _raises(lambda: read_ply(p), FileFormatError, "cloud.ply", name)
    assert time.perf_counter() - t < 2.0, "refused, but not at once"


def test_ply_missing_file(tmp_path):
    _raises(lambda: read_ply(tmp_path / "none.ply"), FileFormatError, "none.ply")


CFG_CASES = [
    ("call", "Namespace(a=os.system('x'))", "'a'"),
    ("name", "Namespace(a=foo)", "'a'"),
    ("attribute", "Namespace(a=os.path)", "'a'"),
    ("lambda", "Namespace(a=lambda: 1)", "'a'"),
    ("100k terms", "Namespace(a=" + "+".join(["1"] * 100_000) + ")", "cfg_args"),
    ("deep list", "Namespace(a=" + "[" * 500 + "]" * 500 + ")", "cfg_args"),
    ("deep list 40", "Namespace(a=" + "[" * 40 + "]" * 40 + ")", "nested"),
    ("2 MB", "Namespace(a='" + "x" * (2 << 20) + "')", "cfg_args"),
    ("not a Namespace", "Other(a=1)", "Namespace"),
    ("syntax error", "Namespace(a=", "Namespace"),
    ("positional", "Namespace(1, a=2)", "positional"),
    ("double star", "Namespace(**d)", "**"),
    ("set of lists", "Namespace(a={[1]})", "'a'"),
    ("empty", "", "cfg_args"),
]


@pytest.mark.parametrize("text, name", [c[1:] for c in CFG_CASES], ids=[c[0] for c in CFG_CASES])
def test_cfg_args(tmp_path, text, name):
    p = tmp_path / "cfg_args"
    p.write_text(text)
    t = time.perf_counter()
    _raises(lambda: read_cfg_args(p), FileFormatError, str(p), name)
    assert time.perf_counter() - t < 2.0


def test_cfg_args_text_names_the_source():
    _raises(lambda: parse_cfg_args("Namespace(a=b)", source="model/cfg_args"), FileFormatError, "model/cfg_args", "'a'")


class _Evil:
    def __reduce__(self):
        return (os.system, ("true",))


@pytest.mark.filterwarnings("ignore:Detected pickle protocol")
@pytest.mark.parametrize("kind", ["pickle", "list", "garbage", "missing"])
def test_state_dict_files(tmp_path, kind):
    p = tmp_path / "checkpoint.pth"
    if kind == "pickle":
        torch.save({"m": _Evil()}, p)
    elif kind == "list":
        torch.save([torch.zeros(1)], p)
    elif kind == "garbage":
        p.write_bytes(b"\x80\x04not a torch file")
    _raises(lambda: load_state_dict_file(p), FileFormatError, "checkpoint.pth")


def test_yaml_config_size_is_bounded(tmp_path):
    p = tmp_path / "config.yaml"
    p.write_text("a: 1\n" * 300_000)
    _raises(lambda: read_yaml_scalars(p), FileFormatError, "config.yaml")


# ============================================================================ files: training checkpoints
@pytest.fixture(scope="module")
def ckpt_setup(tmp_path_factory):
    pytest.importorskip("skimage")
    from controlgs_adapter.backends.models.reference_model import NeuralGaussianModel
    from controlgs_adapter.scene import load_builtin_scene

    scene = load_builtin_scene("ar", 16, views=4, test_every=4, samples=2)
    xyz, rgb = scene.points(0.25)
    model = NeuralGaussianModel.from_points(xyz, rgb, feat_dim=8, n_offsets=2, voxel_size=0.35, color_fit_steps=5).eval()
    return scene, model, tmp_path_factory.mktemp("ckpt")


def _trainer(setup: Any, path: Path, **cfg: Any):
    from controlgs_adapter.training import Trainer

    scene, model, _ = setup
    config = TrainConfig(**{"iterations": 2, "checkpoint_every": 0, "psf_fraction": 0.0, **cfg})
    effects = {"lens": True, "resample": True, "display": True, "oled": True, "optics": {"mode": "distortion"}}
    return Trainer(model, scene.views("train"), config, effects=effects, checkpoint=path)


def _damage(path: Path, header: dict[str, Any] | None = None, tensors: dict[str, Any] | None = None,
            drop: tuple[str, ...] = (), nan: str | None = None) -> None:
    from controlgs_adapter.formats.checkpoint import CHECKPOINT_KIND

    t, h = load_tensors(path, kind=CHECKPOINT_KIND, max_version=1)
    if nan is not None:
        t[nan] = t[nan].clone()
        t[nan].view(-1)[0] = math.nan
    h = {k: v for k, v in h.items() if k not in ("kind", "format_version", "library_version")}
    h.update(header or {})
    t.update(tensors or {})
    for k in drop:
        h.pop(k, None)
        t.pop(k, None)
    write_raw(path, t, h, kind=CHECKPOINT_KIND)


CKPT_CASES = [
    ("rng missing", {"drop": ("rng",)}, "rng"),
    ("rng float", {"tensors": {"rng": torch.zeros(5056)}}, "rng"),
    ("rng short", {"tensors": {"rng": torch.zeros(3, dtype=torch.uint8)}}, "rng"),
    ("param_groups missing", {"drop": ("param_groups",)}, "param_groups"),
    ("param_groups []", {"header": {"param_groups": []}}, "param_groups"),
    ("param_groups wrong params", {"header": {"param_groups": [{"params": [7, 8], "lr": 0.003}]}}, "param_groups"),
    ("param_groups a string", {"header": {"param_groups": "x"}}, "param_groups"),
    ("param_groups of numbers", {"header": {"param_groups": [1]}}, "param_groups"),
    ("param_groups without params", {"header": {"param_groups": [{"lr": 0.003}]}}, "param_groups"),
    ("iteration 'x'", {"header": {"iteration": "x"}}, "iteration"),
    ("iteration -1", {"header": {"iteration": -1}}, "iteration"),
    ("iteration missing", {"drop": ("iteration",)}, "iteration"),
    ("history [nan]", {"header": {"history": [None]}}, "history"),
    ("config a list", {"header": {"config": [1]}}, "config"),
    ("NaN condition", {"nan": "adapter.conditions"}, "NaN"),
    ("NaN Adam state", {"nan": "optimizer.0.exp_avg"}, "NaN"),
    ("adapter tensor missing", {"drop": ("adapter.conditions",)}, "adapter"),
    ("unexpected tensor", {"tensors": {"extra": torch.zeros(1)}}, "extra"),
    ("optimizer key malformed", {"tensors": {"optimizer.x": torch.zeros(1)}}, "optimizer.x"),
    ("optimizer shape", {"tensors": {"optimizer.0.exp_avg": torch.zeros(1)}}, "optimizer.0.exp_avg"),
]


@pytest.mark.parametrize("damage, name", [c[1:] for c in CKPT_CASES], ids=[c[0] for c in CKPT_CASES])
def test_damaged_checkpoint(ckpt_setup, tmp_path, damage, name):
    path = tmp_path / "run.ckpt.safetensors"
    t = _trainer(ckpt_setup, path)
    try:
        t.train(until=1, progress=False)
    finally:
        t.cgs.unwrap()
    _damage(path, **damage)
    fresh = _trainer(ckpt_setup, path)
    try:
        _raises(fresh.resume, FileFormatError, "run.ckpt.safetensors", name)
        assert fresh.iteration == 0
    finally:
        fresh.cgs.unwrap()


def test_training_stops_at_the_first_non_finite_loss_keeping_the_last_checkpoint(ckpt_setup, tmp_path, monkeypatch):
    path = tmp_path / "run.ckpt.safetensors"
    t = _trainer(ckpt_setup, path, iterations=4, checkpoint_every=2)
    try:
        t.train(until=2, progress=False)
        good = path.read_bytes()
        monkeypatch.setattr("controlgs_adapter.training.image_loss", lambda *a, **k: torch.tensor(math.nan, requires_grad=True))
        msg = _raises(lambda: t.train(progress=False), NonFiniteError, "iteration 2")
        assert "loss" in msg
        assert path.read_bytes() == good, "the bad state must not be written"
        assert all(bool(torch.isfinite(p).all()) for p in t.cgs.trainable_parameters())
    finally:
        t.cgs.unwrap()


def test_trainer_constructor_failure_leaves_the_model_unwrapped(ckpt_setup):
    from controlgs_adapter.training import Trainer

    scene, model, _ = ckpt_setup
    with pytest.raises(ControlGSError):
        Trainer(model, scene.views("train"), TrainConfig(iterations=1), effects={"lens": True, "resample": {"bogus": 1}, "display": True})
    assert ControlGS.attached(model) is None


# ============================================================================ CLI
def _cli(argv: list[str], capsys: pytest.CaptureFixture[str]) -> str:
    """Run the CLI in-process: exit code 2, exactly one line on stderr, no traceback; returns it."""
    code = cli.main(argv)
    err = capsys.readouterr().err
    assert code == 2, (code, err)
    lines = err.strip().splitlines()
    assert len(lines) == 1 and "Traceback" not in err, err
    return lines[0]


@pytest.fixture
def files(tmp_path):
    (tmp_path / "bad.json").write_text("{not json")
    (tmp_path / "list.json").write_text("[1, 2]")
    (tmp_path / "field.json").write_text(json.dumps({**CARDBOARD, "display_mm": "66"}))
    (tmp_path / "a_file").write_text("x")
    return tmp_path


CLI_CASES = [
    ("psf-size 4", ["optics", "build-bank", "--psf-size", "4"], "--psf-size"),
    ("psf-size 6", ["optics", "build-bank", "--psf-size", "6"], "--psf-size"),
    ("grid 0 0", ["optics", "build-bank", "--grid", "0", "0"], "--grid"),
    ("grid 3 -1", ["optics", "build-bank", "--grid", "3", "-1"], "--grid"),
    ("pupil-samples 1", ["optics", "build-bank", "--pupil-samples", "1"], "--pupil-samples"),
    ("min-pitch-px 0", ["optics", "build-bank", "--min-pitch-px", "0"], "--min-pitch-px"),
    ("min-pitch-px nan", ["optics", "build-bank", "--min-pitch-px", "nan"], "--min-pitch-px"),
    ("prescription missing", ["optics", "build-bank", "--prescription", "{d}/none.json"], "none.json"),
    ("prescription not JSON", ["optics", "build-bank", "--prescription", "{d}/bad.json"], "bad.json"),
    ("prescription a list", ["optics", "build-bank", "--prescription", "{d}/list.json"], "list.json"),
    ("prescription bad field", ["optics", "build-bank", "--prescription", "{d}/field.json"], "display_mm"),
    ("out a folder", ["optics", "build-bank", "--out", "{d}"], "--out"),
    ("figures prescription missing", ["optics", "figures", "--prescription", "{d}/none.json"], "none.json"),
    ("figures prescription a list", ["optics", "figures", "--prescription", "{d}/list.json"], "list.json"),
    ("demo out under a file", ["demo", "--out", "{d}/a_file/report"], "a_file"),
]


@pytest.mark.parametrize("argv, name", [c[1:] for c in CLI_CASES], ids=[c[0] for c in CLI_CASES])
def test_cli(files, capsys, argv, name):
    line = _cli([a.replace("{d}", str(files)) for a in argv], capsys)
    assert name in line, line


def test_cli_unwritable_out_is_one_line(tmp_path, capsys):
    if os.geteuid() == 0:
        pytest.skip("root writes anywhere")
    ro = tmp_path / "ro"
    ro.mkdir(mode=0o500)
    assert "ro" in _cli(["demo", "--out", str(ro / "report")], capsys)


def test_cli_full_disk_is_one_line(tmp_path, capsys, monkeypatch):
    import errno

    def full(data: Any, tmp: str, metadata: Any = None) -> None:
        Path(tmp).write_bytes(b"half")
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr("controlgs_adapter.formats.safetensors.save_file", full)
    monkeypatch.setattr("controlgs_adapter.downstream.optics.generate.build_bank", lambda *a, **k: tiny_bank())
    line = _cli(["optics", "build-bank", "--out", str(tmp_path / "b.safetensors")], capsys)
    assert "No space left" in line and "b.safetensors" in line
    assert not list(tmp_path.iterdir()), "no partial file left"


class _StandIn(types.ModuleType):
    """What colour-science puts in place of a missing matplotlib: a module without a file."""

    def __getattr__(self, name: str) -> Any:
        raise AttributeError(name)


DEP_CASES = [
    ("demo without matplotlib", ["demo", "--out", "{d}/r"], "matplotlib"),
    ("eval without matplotlib", ["eval", "--run", "{d}/r"], "matplotlib"),
    ("eval --out without matplotlib", ["eval", "--run", "{d}/r", "--out", "{d}/r"], "matplotlib"),
    ("optics bench without matplotlib", ["optics", "bench", "--out", "{d}/r"], "matplotlib"),
    ("scene export without matplotlib", ["scene", "export", "--out", "{d}/r"], "matplotlib"),
    ("demo without scikit-image", ["demo", "--out", "{d}/r"], "scikit-image"),
]


@pytest.mark.parametrize("argv, missing", [c[1:] for c in DEP_CASES], ids=[c[0] for c in DEP_CASES])
def test_missing_optional_dependency_is_checked_first(tmp_path, capsys, monkeypatch, argv, missing):
    if missing == "matplotlib":
        monkeypatch.setitem(sys.modules, "matplotlib", _StandIn("matplotlib"))
    else:
        monkeypatch.setitem(sys.modules, "skimage", None)
    try:
        cli.build_parser().parse_args([a.replace("{d}", str(tmp_path)) for a in argv])
    except SystemExit:
        pytest.fail(f"{argv[0]} no longer parses {argv}: update the case")
    line = _cli([a.replace("{d}", str(tmp_path)) for a in argv], capsys)
    assert missing in line and "controlgs-adapter[demo]" in line, line
    assert not (tmp_path / "r").exists(), "the work must not have started"


def test_cli_error_in_a_fresh_process_has_no_traceback():
    r = subprocess.run([sys.executable, "-m", "controlgs_adapter.cli", "optics", "build-bank", "--psf-size", "4"],
                       capture_output=True, text=True, cwd=ROOT, timeout=120)
    assert r.returncode == 2 and "Traceback" not in r.stderr and len(r.stderr.strip().splitlines()) == 1, r.stderr


# ============================================================================ run-folder lock
_HOLDER = """
import sys, time
from controlgs_adapter.lock import run_lock
with run_lock(sys.argv[1]):
    print("held", flush=True)
    time.sleep(120)
"""


def test_run_folder_lock_refuses_a_second_process_naming_the_holder(tmp_path, capsys):
    run = tmp_path / "run"
    holder = subprocess.Popen([sys.executable, "-c", _HOLDER, str(run)], stdout=subprocess.PIPE, text=True, cwd=ROOT)
    try:
        assert holder.stdout.readline().strip() == "held"
        msg = _raises(lambda: run_lock(run).__enter__(), RunLockedError, str(run), f"pid {holder.pid}")
        assert "since" in msg
        line = _cli(["demo", "--out", str(run)], capsys)  # the CLI too: one line naming the holder
        assert f"pid {holder.pid}" in line
        second = subprocess.run([sys.executable, "-c", _HOLDER, str(run)], capture_output=True, text=True, cwd=ROOT,
                                timeout=120)
        assert second.returncode != 0 and f"pid {holder.pid}" in second.stderr
    finally:
        holder.kill()  # SIGKILL: the kernel drops the lock, the stale .lock file does not block
        holder.wait()
    with run_lock(run):
        assert json.loads((run / ".lock").read_text())["pid"] == os.getpid()


def test_run_lock_is_reentrant_after_release(tmp_path):
    with run_lock(tmp_path):
        pass
    with run_lock(tmp_path):
        pass


# ============================================================================ file modes and partial files
def test_files_get_the_umask_mode(tmp_path, cgs):
    old = os.umask(0o022)
    try:
        p = cgs.save(tmp_path / "sub" / "a.safetensors")
        assert p.stat().st_mode & 0o777 == 0o644
        assert (tmp_path / "sub").stat().st_mode & 0o777 == 0o755
        os.umask(0o027)
        q = atomic_write(tmp_path / "b.txt", lambda t: Path(t).write_text("x"))
        assert q.stat().st_mode & 0o777 == 0o640 and file_mode() == 0o640
    finally:
        os.umask(old)


def test_saved_model_folders_get_the_umask_mode(tmp_path):
    from controlgs_adapter.backends.models.reference_model import NeuralGaussianModel
    from controlgs_adapter.backends.scaffold_io import save_scaffold_dir

    old = os.umask(0o022)
    try:
        model = NeuralGaussianModel.from_points(torch.rand(20, 3), torch.rand(20, 3), feat_dim=8, n_offsets=2,
                                                voxel_size=0.3, color_fit_steps=1)
        final = save_scaffold_dir(model, tmp_path / "m", iteration=1)
        assert final.stat().st_mode & 0o777 == 0o755
        assert all(p.stat().st_mode & 0o777 == 0o644 for p in final.iterdir())
    finally:
        os.umask(old)


def _dead_pid() -> int:
    p = subprocess.Popen([sys.executable, "-c", "pass"])
    p.wait()
    return p.pid


def test_partial_tmp_files_of_killed_writers_are_removed(tmp_path):
    target = tmp_path / "a.safetensors"
    stale = tmp_path / f".a.safetensors.{_dead_pid()}.xyz.tmp"
    stale.write_bytes(b"half")
    live_child = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(60)"])
    try:
        live = tmp_path / f".a.safetensors.{live_child.pid}.abc.tmp"
        live.write_bytes(b"in progress")
        other = tmp_path / f".b.safetensors.{_dead_pid()}.q.tmp"
        other.write_bytes(b"another target's")
        save_tensors(target, {"w": torch.zeros(2)}, {}, kind="k", format_version=1)
        assert not stale.exists(), "a dead writer's partial file must be removed"
        assert live.exists(), "a running writer's file must be left alone"
        assert other.exists(), "only the target's own partial files"
    finally:
        live_child.kill()
        live_child.wait()


def test_a_failed_write_leaves_no_tmp(tmp_path):
    def boom(tmp: str) -> None:
        Path(tmp).write_bytes(b"half")
        raise RuntimeError("killed")

    with pytest.raises(RuntimeError):
        atomic_write(tmp_path / "x.bin", boom)
    assert list(tmp_path.iterdir()) == []


def test_killed_writer_leaves_a_tmp_that_the_next_write_removes(tmp_path):
    script = ("import os, sys, signal\nfrom pathlib import Path\nfrom controlgs_adapter.formats.safetensors import atomic_write\n"
              "def w(t):\n    Path(t).write_bytes(b'half')\n    os.kill(os.getpid(), signal.SIGKILL)\n"
              "atomic_write(sys.argv[1], w)\n")
    r = subprocess.run([sys.executable, "-c", script, str(tmp_path / "x.bin")], cwd=ROOT, timeout=120)
    assert r.returncode == -9
    assert len(list(tmp_path.glob(".x.bin.*.tmp"))) == 1
    atomic_write(tmp_path / "x.bin", lambda t: Path(t).write_bytes(b"whole"))
    assert sorted(p.name for p in tmp_path.iterdir()) == ["x.bin"]


def test_train_refuses_a_locked_run_folder(tmp_path, capsys):
    run = tmp_path / "run"
    with run_lock(run):
        line = _cli(["train", "--out", str(run), "--iterations", "1"], capsys)
    assert f"pid {os.getpid()}" in line and str(run) in line
