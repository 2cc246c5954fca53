"""Backbone file readers: typed cfg_args keys, non-finite weights."""

from __future__ import annotations

import math

import pytest
import torch

from controlgs_adapter.errors import FileFormatError
from controlgs_adapter.formats.backbone import CFG_KEYS, cfg_value, check_finite_weights, parse_cfg_args, read_cfg_args


@pytest.mark.parametrize("entry, key", [
    ("voxel_size='abc'", "voxel_size"), ("voxel_size=nan", "voxel_size"), ("voxel_size=inf", "voxel_size"),
    ("feat_dim='abc'", "feat_dim"), ("feat_dim=32.5", "feat_dim"), ("feat_dim=0", "feat_dim"),
    ("n_offsets=None", "n_offsets"), ("appearance_dim=-1", "appearance_dim"), ("fork=[2]", "fork"),
    ("use_feat_bank='maybe'", "use_feat_bank"), ("add_color_dist=2", "add_color_dist"), ("dist2level=3", "dist2level"),
])
def test_a_key_the_loaders_read_with_a_wrong_value_names_file_and_key(tmp_path, entry, key):
    path = tmp_path / "cfg_args"
    path.write_text(f"Namespace(sh_degree=3, {entry}, model_path='/out')")
    with pytest.raises(FileFormatError, match=rf"^{path}: {key}=.* must be"):
        read_cfg_args(path)


def test_the_keys_the_loaders_read_come_back_typed():
    cfg = parse_cfg_args("Namespace(feat_dim=32.0, n_offsets='10', voxel_size=1, use_feat_bank=0, add_cov_dist='True', "
                         "add_color_dist=False, dist2level='round', far=nan, iteration='abc')")
    assert cfg["feat_dim"] == 32 and isinstance(cfg["feat_dim"], int)
    assert cfg["n_offsets"] == 10 and isinstance(cfg["n_offsets"], int)
    assert cfg["voxel_size"] == 1.0 and isinstance(cfg["voxel_size"], float)
    assert cfg["use_feat_bank"] is False and cfg["add_cov_dist"] is True and cfg["add_color_dist"] is False
    assert cfg["dist2level"] == "round"
    assert math.isnan(cfg["far"]) and cfg["iteration"] == "abc"  # keys no loader reads stay as written
    assert "far" not in CFG_KEYS and "iteration" not in CFG_KEYS


def test_cfg_value_by_hand():
    assert cfg_value("0.5", float, key="k", source="s") == 0.5
    assert cfg_value(True, bool, key="k", source="s") is True
    assert cfg_value("false", bool, key="k", source="s") is False
    with pytest.raises(FileFormatError, match=r"^s: k=True must be a number"):
        cfg_value(True, int, key="k", source="s")
    with pytest.raises(FileFormatError, match=r"^s: k=3 must be at least 4"):
        cfg_value(3, int, key="k", source="s", low=4)


def test_check_finite_weights_names_the_tensor():
    state = {"opacity_mlp": {"0.weight": torch.ones(2, 2), "0.bias": torch.zeros(2)}, "step": torch.tensor(3),
             "bound": [torch.zeros(3), torch.tensor([0.0, math.inf, 1.0])]}
    with pytest.raises(FileFormatError, match=r"^f.pth: tensor 'bound.1' holds 1 NaN/Inf value\(s\) of 3$"):
        check_finite_weights(state, source="f.pth")
    state["bound"][1][1] = 0.0
    check_finite_weights(state, source="f.pth")
    state["opacity_mlp"]["0.bias"][1] = math.nan
    with pytest.raises(FileFormatError, match=r"^f.pth \['x'\]: tensor 'x.opacity_mlp.0.bias' holds 1 NaN/Inf"):
        check_finite_weights(state, source="f.pth ['x']", prefix="x")


import ast
import contextlib
import os
import struct
import subprocess
import sys
import time
import warnings
from pathlib import Path
from typing import Any, Callable

import helpers.octree_files as octree_t
import numpy as np
from helpers.scaffold_oracle import make_raw_model, write_scaffold_dir_by_hand
from hypothesis import given, settings
from hypothesis import strategies as st
from torch import nn

from controlgs_adapter.backends.octree_gs import load_octree_gs_dir
from controlgs_adapter.backends.scaffold_io import load_scaffold_dir
from controlgs_adapter.errors import ControlGSError
from controlgs_adapter.formats import backbone as bb
from controlgs_adapter.formats.backbone import (
    load_state_dict_file,
    load_torchscript,
    load_torchscript_tensors,
    read_ply,
    read_yaml_scalars,
    write_ply,
)
from controlgs_adapter.formats.torchscript import eager_from_archive, tensors_from_archive


def _raises(fn: Callable[[], Any], error: type[BaseException] | tuple[type[BaseException], ...], *names: str) -> str:
    """Call ``fn``; it must raise ``error`` (a ControlGSError) whose message holds every one of ``names``."""
    with pytest.raises(error) as info:
        fn()
    assert isinstance(info.value, ControlGSError), type(info.value)
    msg = str(info.value)
    for n in names:
        assert n in msg, f"{n!r} not in {msg!r}"
    return msg


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


class _Evil:
    def __reduce__(self):
        return (os.system, ("true",))


@pytest.mark.parametrize("data, name", [c[1:] for c in PLY_CASES], ids=[c[0] for c in PLY_CASES])
def test_ply(tmp_path, data, name):
    p = tmp_path / "cloud.ply"
    p.write_bytes(data)
    t = time.perf_counter()
    _raises(lambda: read_ply(p), FileFormatError, "cloud.ply", name)
    assert time.perf_counter() - t < 2.0, "refused, but not at once"


def test_ply_missing_file(tmp_path):
    _raises(lambda: read_ply(tmp_path / "none.ply"), FileFormatError, "none.ply")


@pytest.mark.parametrize("text, name", [c[1:] for c in CFG_CASES], ids=[c[0] for c in CFG_CASES])
def test_cfg_args(tmp_path, text, name):
    p = tmp_path / "cfg_args"
    p.write_text(text)
    t = time.perf_counter()
    _raises(lambda: read_cfg_args(p), FileFormatError, str(p), name)
    assert time.perf_counter() - t < 2.0


def test_cfg_args_text_names_the_source():
    _raises(lambda: parse_cfg_args("Namespace(a=b)", source="model/cfg_args"), FileFormatError, "model/cfg_args", "'a'")


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


@settings(max_examples=15, deadline=None)
@given(st.integers(0, 40), st.integers(1, 6))
def test_ply_round_trip(tmp_path_factory, n, k):
    rng = np.random.default_rng(n * 7 + k)
    fields = {"x": rng.normal(size=n).astype(np.float32), "level": rng.integers(0, 5, n).astype(np.int32),
              **{f"f_offset_{i}": rng.normal(size=n).astype(np.float32) for i in range(3 * k)}}
    p = tmp_path_factory.mktemp("ply") / "a.ply"
    write_ply(p, fields, comments=["standard_dist 2.5"])
    got, comments = read_ply(p)
    assert list(got) == list(fields) and comments == ["standard_dist 2.5"]
    for name in fields:
        np.testing.assert_array_equal(got[name], fields[name])


def test_ply_matches_plyfile_layout_by_hand(tmp_path):
    # an independent writer: header text + packed little-endian records, as plyfile writes them
    vals = np.array([(1.0, 2.0, -3.5), (4.0, 5.5, 6.0)], dtype=[("x", "<f4"), ("y", "<f4"), ("z", "<f4")])
    p = tmp_path / "b.ply"
    p.write_bytes(b"ply\nformat binary_little_endian 1.0\nelement vertex 2\nproperty float x\nproperty float y\n"
                  b"property float z\nend_header\n" + vals.tobytes())
    got, _ = read_ply(p)
    np.testing.assert_array_equal(got["z"], [-3.5, 6.0])


def test_ply_truncated_names_file(tmp_path):
    p = tmp_path / "c.ply"
    write_ply(p, {"x": np.arange(10, dtype=np.float32)})
    p.write_bytes(p.read_bytes()[:-7])
    with pytest.raises(FileFormatError, match="truncated.*10 vertices"):
        read_ply(p)
    (tmp_path / "d.ply").write_bytes(b"ply\nformat binary_little_endian 1.0\nelement vertex 3\n")
    with pytest.raises(FileFormatError, match="end_header"):
        read_ply(tmp_path / "d.ply")


def test_cfg_args_without_eval():
    text = "Namespace(feat_dim=32, n_offsets=10, source_path='/d/x', white_background=False, lod=0, resolution=-1, " \
           "ratio=1, voxel_size=0.001, add_opacity_dist=False, test_iterations=[7000, 30000], far=inf)"
    cfg = parse_cfg_args(text)
    assert cfg["feat_dim"] == 32 and cfg["source_path"] == "/d/x" and cfg["test_iterations"] == [7000, 30000]
    assert cfg["far"] == float("inf")
    with pytest.raises(FileFormatError, match="'weird' must be a Python literal"):  # refused, never run
        parse_cfg_args(text[:-1] + ", weird=os.system('x'))")
    with pytest.raises(FileFormatError):
        parse_cfg_args("__import__('os')")


def test_state_dict_loader_refuses_pickled_objects(tmp_path):
    good = tmp_path / "ok.pth"
    torch.save({"opacity_mlp": {"0.weight": torch.ones(2, 2)}}, good)
    assert torch.equal(load_state_dict_file(good)["opacity_mlp"]["0.weight"], torch.ones(2, 2))
    bad = tmp_path / "bad.pth"
    torch.save({"x": Path("/etc")}, bad)  # a pickled non-tensor object
    with pytest.raises(FileFormatError, match="bad.pth"):
        load_state_dict_file(bad)
    trunc = tmp_path / "trunc.pth"
    trunc.write_bytes(good.read_bytes()[:50])
    with pytest.raises(FileFormatError, match="trunc.pth"):
        load_state_dict_file(trunc)
    with pytest.raises(FileFormatError, match="TorchScript"):
        load_torchscript(good)


# PLY type name -> (struct code, a value that only that type holds exactly)
_TYPES = {
    "char": ("b", -100), "int8": ("b", -7), "uchar": ("B", 200), "uint8": ("B", 255), "short": ("h", -30000),
    "int16": ("h", 1234), "ushort": ("H", 60000), "uint16": ("H", 65535), "int": ("i", -2_000_000_000),
    "int32": ("i", 7), "uint": ("I", 4_000_000_000), "uint32": ("I", 3), "float": ("f", 0.1), "float32": ("f", -2.5),
    "double": ("d", 0.1), "float64": ("d", 1e300),
}


def _ply(path, fmt: str, props: dict[str, tuple[str, str, object]], rows: int, extra_header: str = "") -> None:
    head = f"ply\nformat {fmt} 1.0\ncomment made by hand\nobj_info scanner 7\nelement vertex {rows}\n"
    head += "".join(f"property {t} {n}\n" for n, (t, _, _) in props.items()) + extra_header + "end_header\n"
    if fmt == "ascii":
        body = "".join(" ".join(repr(v) for _, _, v in props.values()) + "\n" for _ in range(rows)).encode()
    else:
        order = "<" if fmt == "binary_little_endian" else ">"
        code = order + "".join(c for _, c, _ in props.values())
        body = b"".join(struct.pack(code, *(v for _, _, v in props.values())) for _ in range(rows))
    path.write_bytes(head.encode() + body)


def _header(tmp_path, lines: str, body: bytes = b""):
    p = tmp_path / "h.ply"
    p.write_bytes(b"ply\n" + lines.encode() + b"end_header\n" + body)
    return p


@pytest.mark.parametrize("fmt", ["binary_little_endian", "binary_big_endian", "ascii"])
def test_every_ply_type_reads_its_value_and_dtype(tmp_path, fmt):
    props = {f"p_{t}": (t, c, v) for t, (c, v) in _TYPES.items()}
    _ply(tmp_path / "a.ply", fmt, props, rows=2)
    fields, comments = bb.read_ply(tmp_path / "a.ply")
    assert comments == ["made by hand", "scanner 7"]
    assert list(fields) == list(props)
    for name, (t, code, v) in props.items():
        want = np.array([v, v], dtype=np.dtype(code))  # struct code == numpy code of that width
        assert fields[name].dtype == want.dtype, name
        assert fields[name].dtype.byteorder in ("=", "|"), name
        np.testing.assert_array_equal(fields[name], want, err_msg=name)
    assert bb.ply_field_names(tmp_path / "a.ply") == list(props)


def test_ply_elements_after_vertex_are_skipped_and_blank_lines_allowed(tmp_path):
    props = {"x": ("float", "f", 1.5), "y": ("double", "d", -2.0)}
    _ply(tmp_path / "a.ply", "binary_little_endian", props, rows=3,
         extra_header="\nelement face 1\nproperty list uchar int vertex_indices\n")
    fields, _ = bb.read_ply(tmp_path / "a.ply")
    assert fields["x"].tolist() == [1.5] * 3 and fields["y"].tolist() == [-2.0] * 3


@pytest.mark.parametrize("lines, words", [
    ("format binary_little_endian 1.0\nelement vertex 1\nproperty float x\nproperty float x\n", "declared twice"),
    ("format binary_little_endian 1.0\nelement vertex 1\nproperty float x\nelement vertex 1\n", "second 'vertex'"),
    ("format binary_little_endian 1.0\nproperty float x\nelement vertex 1\n", "before any 'element vertex'"),
    ("format binary_middle_endian 1.0\nelement vertex 1\nproperty float x\n", "expected 'format"),
    ("format ascii\nelement vertex 1\nproperty float x\n", "expected 'format"),
    ("format ascii 1.0\nelement vertex -1\nproperty float x\n", "non-negative integer count"),
    ("format ascii 1.0\nelement vertex\nproperty float x\n", "non-negative integer count"),
    ("format ascii 1.0\nelement vertex 1\nproperty float\n", "expected 'property <type> <name>'"),
    ("format ascii 1.0\nelement vertex 1\nproperty float x y\n", "expected 'property <type> <name>'"),
    ("format ascii 1.0\nelement vertex 1\nproperty half x\n", "unknown type 'half'"),
    ("format ascii 1.0\nelement vertex 1\nproperty float x\nfoo bar\n", "unknown header keyword 'foo'"),
    ("element vertex 1\nproperty float x\n", "no 'format' line"),
    ("format ascii 1.0\n", "no 'vertex' element"),
    ("format ascii 1.0\nelement vertex 2\n", "no properties"),
    ("format ascii 1.0\nelement face 1\nelement vertex 1\nproperty float x\n", "precedes 'vertex'"),
])
def test_ply_header_refusals_name_file_and_problem(tmp_path, lines, words):
    p = _header(tmp_path, lines)
    with pytest.raises(FileFormatError, match="h.ply") as e:
        bb.read_ply(p)
    assert words in str(e.value)


def test_ply_header_refusal_names_the_line_number(tmp_path):
    p = _header(tmp_path, "format ascii 1.0\ncomment x\nelement vertex 1\nproperty half x\n")
    with pytest.raises(FileFormatError, match="line 5 "):
        bb.read_ply(p)


def test_ply_empty_vertex_element_is_read_as_empty(tmp_path):
    fields, _ = bb.read_ply(_header(tmp_path, "format binary_little_endian 1.0\nelement vertex 0\n"))
    assert fields == {}


def test_ply_not_ply_missing_end_and_oversized_header(tmp_path):
    (tmp_path / "n.ply").write_bytes(b"plx\nformat ascii 1.0\n")
    with pytest.raises(FileFormatError, match="n.ply: not a PLY file"):
        bb.read_ply(tmp_path / "n.ply")
    (tmp_path / "t.ply").write_bytes(b"ply\nformat ascii 1.0\nelement vertex 1\n")
    with pytest.raises(FileFormatError, match=r"t.ply: PLY header ends before 'end_header' \(truncated file, 3 lines\)"):
        bb.read_ply(tmp_path / "t.ply")
    (tmp_path / "big.ply").write_bytes(b"ply\n" + b"comment " + b"x" * 100 + b"\n" * 1 + b"comment y\n" * (bb._PLY_MAX_HEADER // 10))
    with pytest.raises(FileFormatError, match="big.ply: PLY header longer than"):
        bb.read_ply(tmp_path / "big.ply")
    with pytest.raises(FileFormatError, match="nothere.ply: no such file"):
        bb.read_ply(tmp_path / "nothere.ply")


def test_ply_truncated_binary_and_ascii_bodies(tmp_path):
    p = _header(tmp_path, "format binary_big_endian 1.0\nelement vertex 3\nproperty double x\n", b"\0" * 23)
    with pytest.raises(FileFormatError, match=r"h.ply: truncated PLY: header declares 3 vertices x 8 bytes = 24 bytes, "
                                              r"file holds 23 bytes"):
        bb.read_ply(p)
    p.write_bytes(p.read_bytes() + b"\0")
    assert bb.read_ply(p)[0]["x"].tolist() == [0.0] * 3
    # ASCII: exactly the minimum 2*props-1 bytes per vertex passes the size check
    p = _header(tmp_path, "format ascii 1.0\nelement vertex 2\nproperty uchar a\nproperty uchar b\n", b"1 2\n3 4\n")
    assert bb.read_ply(p)[0]["b"].tolist() == [2, 4]
    p = _header(tmp_path, "format ascii 1.0\nelement vertex 3\nproperty uchar a\nproperty uchar b\n", b"1 2\n3 4\n")
    with pytest.raises(FileFormatError, match="h.ply: header declares 3 vertices of 2 values, but only 8 bytes"):
        bb.read_ply(p)
    p = _header(tmp_path, "format ascii 1.0\nelement vertex 2\nproperty uchar a\nproperty uchar b\n", b"1 2 3 4\n5\n")
    with pytest.raises(FileFormatError, match="h.ply: truncated ASCII PLY: vertex 1 has 1 of 2 values"):
        bb.read_ply(p)
    p = _header(tmp_path, "format ascii 1.0\nelement vertex 1\nproperty float a\n", b"abc\n")
    with pytest.raises(FileFormatError, match="h.ply: ASCII PLY vertex data holds a value that is not a number"):
        bb.read_ply(p)


def test_write_ply_bytes_match_a_by_hand_layout(tmp_path):
    x = np.array([1.0, -2.0], np.float64)
    y = np.array([0.5, 0.25], np.float32)
    c = np.array([3, 250], np.uint8)
    s = np.array([-5, 7], np.int16)
    bb.write_ply(tmp_path / "w.ply", {"x": x, "y": y.astype(np.float16), "c": c, "s": s}, ["hello"], comment_keyword="obj_info")
    raw = (tmp_path / "w.ply").read_bytes()
    head = (b"ply\nformat binary_little_endian 1.0\nobj_info hello\nelement vertex 2\nproperty double x\n"
            b"property float y\nproperty uchar c\nproperty short s\nend_header\n")
    body = b"".join(struct.pack("<dfBh", x[i], y[i], c[i], s[i]) for i in range(2))
    assert raw == head + body
    with pytest.raises(FileFormatError, match="write_ply: fields must be 1-D arrays of one length"):
        bb.write_ply(tmp_path / "bad.ply", {"a": np.zeros(2), "b": np.zeros(3)})
    with pytest.raises(FileFormatError, match="write_ply"):
        bb.write_ply(tmp_path / "bad.ply", {"a": np.zeros((2, 2))})


def test_cfg_args_values_and_float_spellings():
    got = bb.parse_cfg_args("Namespace(a=inf, b=-inf, c=nan, d=-3, e=1e-3, f='x', g=[1, (2, 3)], h={'k': None}, "
                            "i=True, j=-0.5)\n")
    assert got["a"] == math.inf and got["b"] == -math.inf and math.isnan(got["c"])
    assert got["d"] == -3 and got["e"] == 0.001 and got["f"] == "x" and got["g"] == [1, (2, 3)]
    assert got["h"] == {"k": None} and got["i"] is True and got["j"] == -0.5
    assert list(got) == list("abcdefghij")


@pytest.mark.parametrize("text, words", [
    ("Namespace(1, a=2)", "positional arguments"),
    ("Namespace(**d)", "'**'"),
    ("Namespace(a=os.system('x'))", "value of 'a' must be a Python literal"),
    ("Namespace(a=infinity)", "value of 'a' must be a Python literal"),
    ("Config(a=1)", "expected 'Namespace(...)'"),
    ("Namespace(a=", "not a printed argparse Namespace"),
    ("Namespace(a=" + "[" * (bb.CFG_MAX_DEPTH + 5) + "]" * (bb.CFG_MAX_DEPTH + 5) + ")", "nested deeper than"),
])
def test_cfg_args_refusals_name_the_source(text, words):
    with pytest.raises(FileFormatError, match="^my_cfg: ") as e:
        bb.parse_cfg_args(text, source="my_cfg")
    assert words in str(e.value)


def test_cfg_args_depth_limit_is_the_documented_one():
    def nested(n: int) -> str:
        return "Namespace(a=" + "[" * n + "]" * n + ")"
    assert bb.parse_cfg_args(nested(bb.CFG_MAX_DEPTH))["a"] is not None
    with pytest.raises(FileFormatError, match="nested deeper"):
        bb.parse_cfg_args(nested(bb.CFG_MAX_DEPTH + 2))


def test_cfg_args_size_limits(tmp_path):
    text = "Namespace(a='" + "x" * bb.CFG_MAX_BYTES + "')"
    with pytest.raises(FileFormatError, match=f"src: {len(text)} characters"):
        bb.parse_cfg_args(text, source="src")
    (tmp_path / "cfg_args").write_text(text)
    with pytest.raises(FileFormatError, match=f"cfg_args: {len(text)} bytes"):
        bb.read_cfg_args(tmp_path / "cfg_args")
    (tmp_path / "cfg_args").write_text("Namespace(sh_degree=3)")
    assert bb.read_cfg_args(tmp_path / "cfg_args") == {"sh_degree": 3}
    with pytest.raises(FileFormatError, match="missing_cfg: no such file"):
        bb.read_cfg_args(tmp_path / "missing_cfg")


def test_yaml_scalars_by_hand(tmp_path):
    (tmp_path / "c.yaml").write_text(
        "# a comment line: ignored\n"
        "model:\n"
        "  feat_dim: 32  # trailing comment\n"
        "  voxel_size: 0.001\n"
        "  name: 'octree: x'\n"
        '  other: "q"\n'
        "  on: True\n"
        "  off: false\n"
        "  nothing: ~\n"
        "  none2: null\n"
        "  iters: 40_000\n"
        "  nested: {a: 1}\n"
        "  items: [1, 2]\n"
        "  word: plain text\n"
        "flow: {\n"
        "  feat_dim: 50,\n"
        "}\n")
    got = bb.read_yaml_scalars(tmp_path / "c.yaml")
    assert got["feat_dim"] == [32, 50] and isinstance(got["feat_dim"][0], int)
    assert got["voxel_size"] == [0.001] and got["name"] == ["octree: x"] and got["other"] == ["q"]
    assert got["on"] == [True] and got["off"] == [False] and got["nothing"] == [None] and got["none2"] == [None]
    assert got["iters"] == [40000] and got["word"] == ["plain text"]
    assert "nested" not in got and "items" not in got and "model" not in got and "flow" not in got


def test_yaml_size_limit_and_missing(tmp_path):
    (tmp_path / "big.yaml").write_bytes(b"a: 1\n" * (bb.YAML_MAX_BYTES // 5 + 1))
    with pytest.raises(FileFormatError, match="big.yaml: .* bytes, more than a config file holds"):
        bb.read_yaml_scalars(tmp_path / "big.yaml")
    with pytest.raises(FileFormatError, match="no.yaml: no such file"):
        bb.read_yaml_scalars(tmp_path / "no.yaml")


def test_ply_columns_numbering_and_count():
    f = {f"f_{i}": np.array([float(i), 10.0 + i]) for i in (0, 1, 2)}
    np.testing.assert_array_equal(bb.ply_columns(f, "f_", source="s"), [[0, 1, 2], [10, 11, 12]])
    np.testing.assert_array_equal(bb.ply_columns(f, "f_", source="s", count=2), [[0, 1], [10, 11]])
    assert bb.ply_columns(f, "f_", source="s").dtype == np.float32
    with pytest.raises(FileFormatError, match=r"src: PLY fields f_\* are not numbered 0..n-1 \(missing f_1\)"):
        bb.ply_columns({"f_0": f["f_0"], "f_2": f["f_2"]}, "f_", source="src")
    with pytest.raises(FileFormatError, match=r"src: PLY fields f_\* are not numbered 0..n-1 \(a number used twice\)"):
        bb.ply_columns({"f_0": f["f_0"], "f_00": f["f_0"]}, "f_", source="src")
    with pytest.raises(FileFormatError, match=r"src: missing PLY field\(s\) \['f_3'\]"):
        bb.ply_columns(f, "f_", source="src", count=4)
    with pytest.raises(FileFormatError, match=r"src: missing PLY field\(s\) \['g_0'\]"):
        bb.ply_columns(f, "g_", source="src", count=0)
    with pytest.raises(FileFormatError, match=r"src: missing PLY field\(s\) \['x', 'z'\]"):
        bb.require_fields({"y": f["f_0"]}, ["x", "y", "z"], source="src")
    with pytest.raises(FileFormatError, match="src: expected 6 f_offset_\\* fields \\(3 x n_offsets=2\\), got 3"):
        bb.ply_offsets({f"f_offset_{i}": f["f_0"] for i in range(3)}, 2, source="src")
    xyz = bb.ply_xyz({"x": np.array([1.0]), "y": np.array([2.0]), "z": np.array([3.0])})
    assert xyz.tolist() == [[1.0, 2.0, 3.0]] and xyz.dtype == np.float32


def test_yaml_hash_inside_a_value_is_not_a_comment(tmp_path):
    (tmp_path / "c.yaml").write_text("tag: v1#2\ncolour: '#ff0000'\nsize: 3 # a comment\n#whole: 1\n")
    assert bb.read_yaml_scalars(tmp_path / "c.yaml") == {"tag": ["v1#2"], "colour": ["#ff0000"], "size": [3]}


def test_big_endian_ply_read_as_big_endian(tmp_path):
    values = {"x": np.array([1.5, -2.25, 3e-3], ">f4"), "level": np.array([1, 2, 300], ">i4"),
              "w": np.array([0.1, 2.0, -7.0], ">f8")}
    header = ("ply\nformat binary_big_endian 1.0\nelement vertex 3\nproperty float x\nproperty int level\n"
              "property double w\nend_header\n")
    table = np.empty(3, dtype=[("x", ">f4"), ("level", ">i4"), ("w", ">f8")])
    for k, v in values.items():
        table[k] = v
    path = tmp_path / "be.ply"
    path.write_bytes(header.encode() + table.tobytes())
    fields, _ = read_ply(path)
    for k, v in values.items():
        assert fields[k].tolist() == v.tolist(), k
        assert fields[k].dtype.isnative


def _good(tmp_path, mode="split"):
    raw = make_raw_model(8, 8, 3, seed=9)
    return raw, write_scaffold_dir_by_hand(tmp_path, raw, mode=mode)


@pytest.mark.parametrize("drop", ["scale_5", "f_offset_4", "rot_0", "y"])
def test_missing_ply_field_names_it(tmp_path, drop):
    raw, folder = _good(tmp_path)
    ply = folder / "point_cloud.ply"
    fields, _ = read_ply(ply)
    del fields[drop]
    from controlgs_adapter.formats.backbone import write_ply

    write_ply(ply, fields)
    with pytest.raises(FileFormatError, match=rf"point_cloud\.ply.*{drop}"):
        load_scaffold_dir(tmp_path)


def test_offset_fields_not_numbered_contiguously_are_refused(tmp_path):
    raw, folder = _good(tmp_path)
    ply = folder / "point_cloud.ply"
    fields, _ = read_ply(ply)
    fields = {("f_offset_99" if n == "f_offset_2" else n): v for n, v in fields.items()}
    from controlgs_adapter.formats.backbone import write_ply

    write_ply(ply, fields)
    with pytest.raises(FileFormatError, match=r"point_cloud\.ply.*f_offset_2"):
        load_scaffold_dir(tmp_path)


def _header_2(path) -> list[str]:
    raw = path.read_bytes()
    return raw[:raw.index(b"end_header\n")].decode("ascii").splitlines()


def test_parse_cfg_args_default_source_is_cfg_args():
    with pytest.raises(FileFormatError, match=r"^cfg_args: not a printed argparse Namespace"):
        parse_cfg_args("Namespace(a=")
    with pytest.raises(FileFormatError, match=r"^run/cfg: not a printed argparse Namespace"):
        parse_cfg_args("Namespace(a=", source="run/cfg")


def test_write_ply_default_comments_none_and_keyword_comment(tmp_path):
    fields = {"x": np.arange(3, dtype=np.float32)}
    plain = _header_2(write_ply(tmp_path / "a.ply", fields))
    assert plain == ["ply", "format binary_little_endian 1.0", "element vertex 3", "property float x"]
    noted = _header_2(write_ply(tmp_path / "b.ply", fields, ["made by hand"]))
    assert noted[2] == "comment made by hand" and len(noted) == 5
    other = _header_2(write_ply(tmp_path / "c.ply", fields, ["x"], comment_keyword="obj_info"))
    assert other[2] == "obj_info x"


def test_ply_columns_default_count_takes_every_numbered_column():
    from controlgs_adapter.formats.backbone import ply_columns

    fields = {"f_0": np.array([1.0, 2.0]), "f_2": np.array([5.0, 6.0]), "f_1": np.array([3.0, 4.0]),
              "f_rest": np.array([9.0, 9.0]), "x": np.zeros(2)}
    got = ply_columns(fields, "f_", source="a.ply")
    assert got.dtype == np.float32 and got.tolist() == [[1.0, 3.0, 5.0], [2.0, 4.0, 6.0]]
    assert ply_columns(fields, "f_", source="a.ply", count=2).tolist() == [[1.0, 3.0], [2.0, 4.0]]
    del fields["f_1"]
    with pytest.raises(FileFormatError, match=r"^a.ply: PLY fields f_\* are not numbered 0..n-1 \(missing f_1\)$"):
        ply_columns(fields, "f_", source="a.ply")


# ------------------------------------------------------------------------------ weights-only loading
_SAVE_AS_CUDA = """
import sys, torch
# tag every storage as if it had been saved on a GPU (this machine may have none)
torch.serialization.register_package(1, lambda obj: "cuda:0" if obj.device.type == "cpu" else None,
                                     lambda obj, location: None)
torch.save({"w": torch.arange(6, dtype=torch.float32).reshape(2, 3), "n": 3}, sys.argv[1])
"""


def test_state_dict_saved_on_a_gpu_loads_onto_the_cpu(tmp_path):
    """``load_state_dict_file`` reads on the CPU: a checkpoint whose tensors were saved on ``cuda:0`` loads
    with CPU tensors, whether or not this machine has a GPU."""
    path = tmp_path / "gpu.pt"
    subprocess.run([sys.executable, "-c", _SAVE_AS_CUDA, str(path)], check=True, timeout=120)
    assert b"cuda:0" in path.read_bytes()
    obj = load_state_dict_file(path)
    assert obj["n"] == 3 and obj["w"].device == torch.device("cpu")
    assert torch.equal(obj["w"], torch.arange(6, dtype=torch.float32).reshape(2, 3))


# ------------------------------------------------------------------------------ Octree-GS anchor PLY
def test_octree_gs_anchor_ply_keeps_six_scales_when_other_tools_add_scale_columns(tmp_path):
    """Octree-GS anchors have six scales (``scale_0..5``: offset extent and Gaussian size); a PLY carrying a
    further ``scale_6`` column (appended by another tool) still loads as ``[A, 6]`` from the first six."""
    from helpers.octree_files import _arrays, _decoders, _write_dir

    from controlgs_adapter.backends.octree_gs import load_octree_gs_dir

    arr = _arrays(1)
    _write_dir(tmp_path, arr, _decoders(torch.Generator().manual_seed(1)))
    ply = tmp_path / "point_cloud" / "iteration_30000" / "point_cloud.ply"
    fields, _ = read_ply(ply)
    write_ply(ply, {**fields, "scale_6": np.full(len(fields["x"]), 9.0, np.float32)})
    model = load_octree_gs_dir(tmp_path)
    assert torch.equal(model._scaling, torch.from_numpy(arr["scale"]))


def test_octree_folder_with_two_anchors_loads_voxel_size_and_standard_dist_from_info(tmp_path):
    """Octree-GS keeps voxel_size and standard_dist in rows 0 and 1 of the 'info' column: a file with exactly
    two anchors holds both and loads, with those two values."""
    arr = octree_t._arrays(2)
    decs = octree_t._decoders(torch.Generator().manual_seed(2))
    root = octree_t._write_dir(tmp_path / "o", arr, decs, mode="unite")
    ply = root / "point_cloud" / "iteration_30000" / "point_cloud.ply"
    fields, _ = read_ply(ply)
    write_ply(ply, {n: np.ascontiguousarray(c[:2]) for n, c in fields.items()})
    m = load_octree_gs_dir(root)
    assert m.get_anchor.shape[0] == 2
    assert m.voxel_size == pytest.approx(octree_t.VOXEL, rel=1e-6)
    assert m.standard_dist == pytest.approx(octree_t.STD_DIST, rel=1e-6)


def test_octree_anygs_defaults_for_keys_missing_from_config_yaml(tmp_path):
    """Octree-AnyGS's GaussianLoDModel defaults: feat_dim 32, n_offsets 10, fork 2, dist2level 'round',
    base model Scaffold-GS: a config.yaml naming none of them reads a folder of those widths."""
    from controlgs_adapter.formats.backbone import write_ply

    a, f, k = 6, 32, 10
    rng = np.random.default_rng(0)
    root = tmp_path / "anygs"
    it = root / "point_cloud" / "iteration_5"
    it.mkdir(parents=True)
    (root / "config.yaml").write_text("optim_params: {\n    iterations: 40_000,\n}\n")
    fields = {c: rng.normal(size=a).astype(np.float32) for c in "xyz"}
    fields.update(level=np.zeros(a, np.float32), extra_level=np.zeros(a, np.float32))
    fields.update({f"f_offset_{i}": rng.normal(size=a).astype(np.float32) for i in range(3 * k)})
    fields.update({f"f_anchor_feat_{i}": rng.normal(size=a).astype(np.float32) for i in range(f)})
    fields.update({f"scale_{i}": np.full(a, -2.0, np.float32) for i in range(6)})
    write_ply(it / "point_cloud.ply", fields, comments=["standard_dist 3.0", "levels 2"], comment_keyword="obj_info")
    torch.manual_seed(0)
    torch.save({"opacity_mlp": nn.Sequential(nn.Linear(f + 3, f), nn.ReLU(), nn.Linear(f, k), nn.Tanh()).state_dict(),
                "cov_mlp": nn.Sequential(nn.Linear(f + 3, f), nn.ReLU(), nn.Linear(f, 7 * k)).state_dict(),
                "color_mlp": nn.Sequential(nn.Linear(f + 3, f), nn.ReLU(), nn.Linear(f, 3 * k), nn.Sigmoid()).state_dict()},
               it / "checkpoints.pth")
    m = load_octree_gs_dir(root)
    assert (m.feat_dim, m.n_offsets, m.fork, m.dist2level, m.levels, m.standard_dist) == (32, 10, 2, "round", 2, 3.0)
    assert not m.voxel_centre and m.voxel_size == 0.0
    # the LOD header lines are required
    write_ply(it / "point_cloud.ply", fields, comments=["standard_dist 3.0"], comment_keyword="obj_info")
    with pytest.raises(FileFormatError, match="must carry 'obj_info standard_dist <v>' and 'obj_info levels <v>'"):
        load_octree_gs_dir(root)


def _scaffold_folder(tmp_path, mode="unite"):
    raw = make_raw_model(5, 8, 2, seed=4)
    return write_scaffold_dir_by_hand(tmp_path / "s", raw, mode=mode), raw


def test_ply_refusals_name_the_field(tmp_path):
    from controlgs_adapter.formats.backbone import read_ply, write_ply

    folder, _ = _scaffold_folder(tmp_path)
    ply = folder / "point_cloud.ply"
    fields, _ = read_ply(ply)
    write_ply(ply, {**fields, "opacity": np.arange(5, dtype=np.int32)})
    with pytest.raises(FileFormatError, match=r"point_cloud.ply: PLY field 'opacity' must be float, got int32"):
        load_scaffold_dir(tmp_path / "s")
    write_ply(ply, {k: v for k, v in fields.items() if k != "f_offset_5"})
    with pytest.raises(FileFormatError, match=r"5 PLY fields f_offset_\* is not 3 x n_offsets"):
        load_scaffold_dir(tmp_path / "s")
    write_ply(ply, {**fields, "scale_6": fields["scale_0"]})
    with pytest.raises(FileFormatError, match=r"expected PLY fields scale_0..scale_5 and rot_0..rot_3, got 7 scale_\* "
                                              r"and 4 rot_\*"):
        load_scaffold_dir(tmp_path / "s")
    write_ply(ply, {**fields, "rot_4": fields["rot_0"]})
    with pytest.raises(FileFormatError, match=r"got 6 scale_\* and 5 rot_\*"):
        load_scaffold_dir(tmp_path / "s")


def test_cfg_args_term_budget_is_100000_nodes():
    # Namespace(a=[0, ..., 0]) with k zeros: Call, Name, Load, keyword, List, Load and k Constants = k + 6 nodes
    k = 100_000 - 6
    text = f"Namespace(a=[{', '.join(['0'] * k)}])"
    assert sum(1 for _ in ast.walk(ast.parse(text, mode="eval").body)) == 100_000  # brute-force count
    assert bb.parse_cfg_args(text, source="big")["a"] == [0] * k
    text = f"Namespace(a=[{', '.join(['0'] * (k + 1))}])"  # one node more
    with pytest.raises(FileFormatError, match=r"^over: nested deeper than 32 levels or longer than 100000 terms"):
        bb.parse_cfg_args(text, source="over")


def test_cfg_args_text_size_bound_is_1_mib():
    pad = " " * ((1 << 20) - len("Namespace(a=1)"))
    assert bb.parse_cfg_args("Namespace(a=1)" + pad) == {"a": 1}  # exactly 1 MiB: read
    with pytest.raises(FileFormatError, match=r"1048577 characters, more than a cfg_args holds \(<= 1048576\)"):
        bb.parse_cfg_args("Namespace(a=1)" + pad + " ")


def test_ascii_ply_smallest_body_passes_the_size_check(tmp_path):
    # two vertices of two values: the smallest body is "1 2\n3 4" (7 bytes, no final newline); the
    # pre-check asks for count * (2 * props - 1) = 6 bytes, so this file must be read
    p = tmp_path / "a.ply"
    p.write_bytes(b"ply\nformat ascii 1.0\nelement vertex 2\nproperty float x\nproperty uchar c\nend_header\n1 2\n3 4")
    fields, _ = bb.read_ply(p)
    assert fields["x"].tolist() == [1.0, 3.0] and fields["x"].dtype == np.float32
    assert fields["c"].tolist() == [2, 4] and fields["c"].dtype == np.uint8
    # one byte short of the pre-check's 6: refused before reading, naming the numbers
    p.write_bytes(b"ply\nformat ascii 1.0\nelement vertex 2\nproperty float x\nproperty uchar c\nend_header\n1 2 3")
    with pytest.raises(FileFormatError, match=r"a\.ply: header declares 2 vertices of 2 values, but only 5 bytes follow"):
        bb.read_ply(p)
    # extra values on a line are ignored, only the declared ones are read
    p.write_bytes(b"ply\nformat ascii 1.0\nelement vertex 1\nproperty double x\nend_header\n0.5 9 9\n")
    fields, _ = bb.read_ply(p)
    assert fields["x"].tolist() == [0.5] and fields["x"].dtype == np.float64


def test_ply_offsets_layout_by_hand():
    # K = 2 offsets: f_offset_{c*K + k} is coordinate c of offset k, so vertex 0's offsets are
    # k=0: (f0, f2, f4) and k=1: (f1, f3, f5)
    fields = {f"f_offset_{i}": np.array([float(i), 10.0 + i]) for i in range(6)}
    got = bb.ply_offsets(fields, 2, source="s")
    assert got.shape == (2, 2, 3) and got.dtype == np.float32
    assert got[0].tolist() == [[0.0, 2.0, 4.0], [1.0, 3.0, 5.0]]
    assert got[1].tolist() == [[10.0, 12.0, 14.0], [11.0, 13.0, 15.0]]
    assert got.flags["C_CONTIGUOUS"]


def test_state_dict_file_must_be_a_dict(tmp_path):
    import torch

    torch.save([torch.zeros(2)], tmp_path / "l.pth")
    with pytest.raises(FileFormatError, match=r"l\.pth: expected a dict of state dicts, got list"):
        bb.load_state_dict_file(tmp_path / "l.pth")
    with pytest.raises(FileFormatError, match=r"none\.pth: no such file"):
        bb.load_state_dict_file(tmp_path / "none.pth")
    torch.save({"a": {"w": torch.ones(2)}}, tmp_path / "d.pth")
    assert torch.equal(bb.load_state_dict_file(tmp_path / "d.pth")["a"]["w"], torch.ones(2))


@pytest.mark.filterwarnings("ignore::DeprecationWarning")
def test_trusted_torchscript_paths_name_the_file(tmp_path):
    """``trust_code=True`` on archives this test wrote itself (the opt-in path: ``torch.jit.load``)."""
    import warnings

    import torch
    from torch import nn


    with pytest.raises(FileFormatError, match=r"gone\.pt: no such file"):
        bb.load_torchscript(tmp_path / "gone.pt", trust_code=True)
    with pytest.raises(FileFormatError, match=r"gone\.pt: no such file"):
        bb.load_torchscript_tensors(tmp_path / "gone.pt", trust_code=True)
    (tmp_path / "junk.pt").write_bytes(b"not a zip at all")
    with pytest.raises(FileFormatError, match=r"junk\.pt: not a loadable TorchScript archive \(truncated\?\)"):
        bb.load_torchscript(tmp_path / "junk.pt", trust_code=True)
    # without trust_code the same files are refused by the data reader, never returned as None
    with pytest.raises(FileFormatError, match=r"gone\.pt: no such file"):
        tensors_from_archive(tmp_path / "gone.pt")
    with pytest.raises(FileFormatError, match=r"junk\.pt: not a TorchScript archive \(not a zip file"):
        tensors_from_archive(tmp_path / "junk.pt")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        torch.jit.save(torch.jit.script(nn.Sequential(nn.Linear(3, 2), nn.GELU())), str(tmp_path / "gelu.pt"))
        lin = nn.Sequential(nn.Linear(3, 2), nn.Sigmoid())
        torch.jit.save(torch.jit.trace(lin, torch.randn(2, 3)), str(tmp_path / "ok.pt"))
    with pytest.raises(FileFormatError, match=r"gelu\.pt: TorchScript decoder cannot be rebuilt as an eager module: .*GELU"):
        bb.load_torchscript(tmp_path / "gelu.pt", trust_code=True)
    got = bb.load_torchscript(tmp_path / "ok.pt", trust_code=True)
    x = torch.randn(4, 3)
    assert not isinstance(got, torch.jit.ScriptModule) and torch.equal(got(x), lin(x))
    sd = bb.load_torchscript_tensors(tmp_path / "ok.pt", trust_code=True)
    assert list(sd) == ["0.weight", "0.bias"] and torch.equal(sd["0.weight"], lin[0].weight)
    assert not sd["0.weight"].requires_grad


def test_cfg_args_nesting_bound_is_32_levels():
    # Namespace(a=[[...]]) with n lists: Call (depth 0), keyword (1), lists (2 .. n + 1), the innermost
    # list's Load (n + 2); the reader allows depth <= 32 + 2, so n = 32 is read and n = 33 refused
    def nested(n: int) -> str:
        return "Namespace(a=" + "[" * n + "]" * n + ")"

    got = bb.parse_cfg_args(nested(32))["a"]
    for _ in range(31):
        got = got[0]
    assert got == []
    with pytest.raises(FileFormatError, match=r"^cfg_args: nested deeper than 32 levels or longer than 100000 terms; "
                                              r"not a printed argparse Namespace$"):
        bb.parse_cfg_args(nested(33))


def test_file_size_bounds_are_1_mib(tmp_path):
    mib = 1 << 20
    # cfg_args files
    p = tmp_path / "cfg_args"
    p.write_text("Namespace(a=1)" + " " * (mib - len("Namespace(a=1)")))
    assert bb.read_cfg_args(p) == {"a": 1}
    p.write_text("Namespace(a=1)" + " " * (mib + 1 - len("Namespace(a=1)")))
    with pytest.raises(FileFormatError, match=r"cfg_args: 1048577 bytes, more than a cfg_args holds \(<= 1048576\)"):
        bb.read_cfg_args(p)
    # YAML configs
    y = tmp_path / "c.yaml"
    y.write_text("a: 1\n" + "#" * (mib - 6) + "\n")
    assert bb.read_yaml_scalars(y) == {"a": [1]}
    y.write_text("a: 1\n" + "#" * (mib - 5) + "\n")
    with pytest.raises(FileFormatError, match=r"c\.yaml: 1048577 bytes, more than a config file holds \(<= 1048576\)"):
        bb.read_yaml_scalars(y)
    # PLY headers: up to 1 MiB including the end_header line
    head, tail = b"ply\nformat binary_little_endian 1.0\nelement vertex 0\ncomment ", b"\nend_header\n"
    ply = tmp_path / "h.ply"
    ply.write_bytes(head + b"x" * (mib - len(head) - len(tail)) + tail)
    assert bb.read_ply(ply) == ({}, ["x" * (mib - len(head) - len(tail))])
    ply.write_bytes(head + b"x" * (mib + 1 - len(head) - len(tail)) + tail)
    with pytest.raises(FileFormatError, match=r"h\.ply: PLY header longer than 1048576 bytes without 'end_header'"):
        bb.read_ply(ply)


def test_yaml_scalars_survive_bytes_that_are_not_utf8(tmp_path):
    """Octree-AnyGS configs are read as text with undecodable bytes replaced (a Latin-1 comment or
    path), not refused with a UnicodeDecodeError."""
    from controlgs_adapter.formats.backbone import read_yaml_scalars

    path = tmp_path / "config.yaml"
    path.write_bytes(b"# caf\xe9 scene\nmodel:\n  voxel_size: 0.01  # m\xe9tres\n  name: sc\xe8ne\n")
    assert read_yaml_scalars(path) == {"voxel_size": [0.01], "name": ["sc\ufffdne"]}


_JIT_ALLOWED = [False]


@contextlib.contextmanager
def _jit_allowed():
    """Where the test itself loads an archive it trusts (reference outputs, ``trust_code=True``)."""
    _JIT_ALLOWED[0] = True
    try:
        yield
    finally:
        _JIT_ALLOWED[0] = False


def _save(module: nn.Module, path: Path, mode: str, in_features: int) -> Path:
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        sm = torch.jit.trace(module, torch.randn(3, in_features)) if mode == "trace" else torch.jit.script(module)
        torch.jit.save(sm, str(path))
    return path


def _reference(path: Path) -> torch.jit.ScriptModule:
    """The archive this test made itself, loaded the trusted way, to get the reference outputs."""
    with warnings.catch_warnings(), _jit_allowed():
        warnings.simplefilter("ignore")
        return torch.jit.load(str(path))


class _Embedding(nn.Module):  # Scaffold-GS's scene/embedding.py wrapper
    def __init__(self) -> None:
        super().__init__()
        self.embedding = nn.Embedding(7, 32)

    def forward(self, idx: torch.Tensor) -> torch.Tensor:
        return self.embedding(idx)


class Writer(nn.Module):
    """``forward`` overwrites ``target`` (``torch.from_file(path, True, n)``) and returns a Linear's output."""

    def __init__(self, target: str) -> None:
        super().__init__()
        self.lin = nn.Linear(4, 4)
        self.target = target

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        t = torch.from_file(self.target, True, 8, dtype=torch.uint8)
        t.fill_(65)
        return self.lin(x) + t[:1].float() * 0


def _refused(path: Path, *what: str) -> FileFormatError:
    with pytest.raises(FileFormatError) as info:
        eager_from_archive(path)
    msg = str(info.value)
    assert str(path) in msg, msg
    for w in what:
        assert w in msg, msg
    return info.value


def test_appearance_embedding_tensors(tmp_path):
    path = tmp_path / "embedding_appearance.pt"
    torch.jit.trace(_Embedding(), torch.zeros(3, dtype=torch.long)).save(str(path))
    got = load_torchscript_tensors(path)
    want = _reference(path).state_dict()
    assert got.keys() == want.keys() == {"embedding.weight"} and torch.equal(got["embedding.weight"], want["embedding.weight"])
    with _jit_allowed():
        trusted = load_torchscript_tensors(path, trust_code=True)
    assert torch.equal(trusted["embedding.weight"], want["embedding.weight"])


def test_forward_that_writes_a_file_is_refused_and_never_runs(tmp_path):
    target = tmp_path / "victim"
    path = tmp_path / "opacity_mlp.pt"
    torch.jit.script(Writer(str(target))).save(str(path))
    _refused(path, "Writer")
    with pytest.raises(FileFormatError, match="opacity_mlp.pt"):
        load_torchscript(path)
    assert not target.exists()


def test_trust_code_is_an_explicit_opt_in_never_a_fallback(tmp_path):
    class Sequential(nn.Sequential):  # outside the safe subset (a class of its own), harmless
        @torch.jit.export
        def extra(self) -> int:
            return 1

    dec = Sequential(nn.Linear(4, 4), nn.ReLU())
    path = _save(dec, tmp_path / "opacity_mlp.pt", "script", 4)
    with pytest.raises(FileFormatError, match="opacity_mlp.pt"):
        load_torchscript(path)  # the default never falls back to torch.jit.load
    x = torch.randn(3, 4)
    with _jit_allowed():
        trusted = load_torchscript(path, trust_code=True)
    assert torch.equal(trusted(x), dec(x))


pytestmark = pytest.mark.filterwarnings("ignore::DeprecationWarning")
