"""The files of a trained backbone folder (``formats.backbone``), read as data: PLY point clouds (every
type and layout, bounded and checked header and body), cfg_args (literals only, typed keys, bounded),
YAML configs, weights-only state dicts and TorchScript decoders (``trust_code`` an explicit opt-in)."""

from __future__ import annotations

import ast
import math
import os
import struct
import subprocess
import sys
import warnings
from pathlib import Path

import numpy as np
import pytest
import torch
from helpers.scaffold_oracle import Embedding
from hypothesis import given, settings
from hypothesis import strategies as st
from torch import nn

from controlgs_adapter.errors import FileFormatError
from controlgs_adapter.formats import backbone as bb
from controlgs_adapter.formats.backbone import (
    CFG_KEYS,
    cfg_value,
    check_finite_weights,
    load_state_dict_file,
    load_torchscript,
    load_torchscript_tensors,
    parse_cfg_args,
    ply_columns,
    read_cfg_args,
    read_ply,
    read_yaml_scalars,
    write_ply,
)
from controlgs_adapter.formats.torchscript import tensors_from_archive

pytestmark = pytest.mark.filterwarnings("ignore::DeprecationWarning")

MIB = 1 << 20


def _trusted(path: Path) -> torch.jit.ScriptModule:
    """An archive this test made itself, loaded the trusted way, for reference outputs."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return torch.jit.load(str(path))


# ---------------------------------------------------------------------------------------------- PLY
HEAD = b"ply\nformat binary_little_endian 1.0\n"

#: (id, file bytes, what the refusal names besides the file)
PLY_REFUSALS = [
    ("not ply", b"plx\n", "not a PLY file"),
    ("no end_header", HEAD + b"element vertex 1\nproperty float x\n", "ends before 'end_header' (truncated file, 4 lines)"),
    ("ascii 10M vertices in 84 bytes", b"ply\nformat ascii 1.0\nelement vertex 10000000\nproperty float x\n"
                                       b"property float y\nend_header\n1 2\n", "10000000 vertices of 2 values, but only 4 bytes"),
    ("binary 1e11 vertices", HEAD + b"element vertex 100000000000\nproperty float x\nend_header\n\0\0\0\0",
     "100000000000 vertices x 4 bytes = 400000000000 bytes, file holds 4 bytes"),
    ("binary truncated", HEAD + b"element vertex 4\nproperty float x\nend_header\n" + b"\0" * 10,
     "truncated PLY: header declares 4 vertices x 4 bytes = 16 bytes, file holds 10 bytes"),
    ("count 'abc'", HEAD + b"element vertex abc\nproperty float x\nend_header\n", "line 3 'element vertex abc'"),
    ("count -5", HEAD + b"element vertex -5\nproperty float x\nend_header\n", "line 3 'element vertex -5'"),
    ("count 1e3", HEAD + b"element vertex 1e3\nproperty float x\nend_header\n", "line 3 'element vertex 1e3'"),
    ("count missing", HEAD + b"element vertex\nproperty float x\nend_header\n", "line 3 'element vertex'"),
    ("unknown type", HEAD + b"element vertex 1\nproperty float128 x\nend_header\n", "line 4 'property float128 x'"),
    ("type half", b"ply\nformat ascii 1.0\ncomment x\nelement vertex 1\nproperty half x\nend_header\n", "line 5 'property half x'"),
    ("property 2 words", HEAD + b"element vertex 1\nproperty float\nend_header\n", "line 4 'property float'"),
    ("property 4 words", HEAD + b"element vertex 1\nproperty float x y\nend_header\n", "line 4 'property float x y'"),
    ("list in vertex", HEAD + b"element vertex 1\nproperty list uchar int idx\nend_header\n", "list property 'idx'"),
    ("format bogus", b"ply\nformat binary_middle_endian 1.0\nelement vertex 0\nend_header\n", "line 2 'format binary_middle_endian"),
    ("format 2 words", b"ply\nformat ascii\nelement vertex 0\nend_header\n", "line 2 'format ascii'"),
    ("no format", b"ply\nelement vertex 1\nproperty float x\nend_header\n\0\0\0\0", "no 'format' line"),
    ("no vertex", HEAD + b"end_header\n", "no 'vertex' element"),
    ("face before vertex", HEAD + b"element face 1\nproperty list uchar int i\nelement vertex 1\nend_header\n",
     "line 3 'element face 1': element 'face' precedes 'vertex'"),
    ("property before element", HEAD + b"property float x\nelement vertex 1\nend_header\n",
     "line 3 'property float x': 'property' before any 'element vertex'"),
    ("duplicate property", HEAD + b"element vertex 1\nproperty float x\nproperty float x\nend_header\n",
     "line 5 'property float x': property 'x' declared twice"),
    ("two vertex elements", HEAD + b"element vertex 1\nproperty float x\nelement vertex 1\nend_header\n",
     "line 5 'element vertex 1': a second 'vertex' element"),
    ("unknown keyword", HEAD + b"elemnt vertex 1\nend_header\n", "line 3 'elemnt vertex 1': unknown header keyword 'elemnt'"),
    ("vertex without properties", HEAD + b"element vertex 5\nend_header\n", "declares 5 vertices but no properties"),
    ("ascii not a number", b"ply\nformat ascii 1.0\nelement vertex 1\nproperty float x\nend_header\nabc\n",
     "ASCII PLY vertex data holds a value that is not a number"),
    ("ascii short row", b"ply\nformat ascii 1.0\nelement vertex 2\nproperty float x\nproperty float y\nend_header\n"
                        b"1 2\n3\n", "vertex 1 has 1 of 2 values"),
    ("header of 2 MB", b"ply\n" + b"comment " + b"x" * (2 << 20) + b"\n", "PLY header longer than 1048576 bytes"),
]


@pytest.mark.parametrize("data, words", [c[1:] for c in PLY_REFUSALS], ids=[c[0] for c in PLY_REFUSALS])
def test_ply_refusals_name_the_file_and_the_problem(tmp_path, data, words):
    """Malformed headers name the line; declared sizes the body cannot hold are refused before reading it."""
    p = tmp_path / "cloud.ply"
    p.write_bytes(data)
    with pytest.raises(FileFormatError) as e:
        read_ply(p)
    assert str(e.value).startswith(f"{p}: ") and words in str(e.value), str(e.value)


def test_ply_header_bound_is_1_mib_and_a_missing_file_is_named(tmp_path):
    # up to 1 MiB including the end_header line
    head, tail = b"ply\nformat binary_little_endian 1.0\nelement vertex 0\ncomment ", b"\nend_header\n"
    ply = tmp_path / "h.ply"
    ply.write_bytes(head + b"x" * (MIB - len(head) - len(tail)) + tail)
    assert read_ply(ply) == ({}, ["x" * (MIB - len(head) - len(tail))])
    ply.write_bytes(head + b"x" * (MIB + 1 - len(head) - len(tail)) + tail)
    with pytest.raises(FileFormatError, match=r"h\.ply: PLY header longer than 1048576 bytes without 'end_header'"):
        read_ply(ply)
    with pytest.raises(FileFormatError, match="nothere.ply: no such file"):
        read_ply(tmp_path / "nothere.ply")


def test_ply_body_size_is_checked_against_the_header(tmp_path):
    def body(lines: str, data: bytes) -> Path:
        p = tmp_path / "b.ply"
        p.write_bytes(b"ply\n" + lines.encode() + b"end_header\n" + data)
        return p

    p = body("format binary_big_endian 1.0\nelement vertex 3\nproperty double x\n", b"\0" * 23)
    with pytest.raises(FileFormatError, match=r"b.ply: truncated PLY: header declares 3 vertices x 8 bytes = 24 bytes, "
                                              r"file holds 23 bytes"):
        read_ply(p)
    p.write_bytes(p.read_bytes() + b"\0")
    assert read_ply(p)[0]["x"].tolist() == [0.0] * 3
    # ASCII: two vertices of two values need at least 2 * (2 * 2 - 1) = 6 bytes; "1 2\n3 4" (7, no final newline) is read
    two = "format ascii 1.0\nelement vertex 2\nproperty float x\nproperty uchar c\n"
    fields, _ = read_ply(body(two, b"1 2\n3 4"))
    assert fields["x"].tolist() == [1.0, 3.0] and fields["x"].dtype == np.float32
    assert fields["c"].tolist() == [2, 4] and fields["c"].dtype == np.uint8
    with pytest.raises(FileFormatError, match=r"b\.ply: header declares 2 vertices of 2 values, but only 5 bytes follow"):
        read_ply(body(two, b"1 2 3"))
    with pytest.raises(FileFormatError, match="b.ply: header declares 3 vertices of 2 values, but only 8 bytes"):
        read_ply(body(two.replace("vertex 2", "vertex 3"), b"1 2\n3 4\n"))
    # extra values on a line are ignored, only the declared ones are read
    fields, _ = read_ply(body("format ascii 1.0\nelement vertex 1\nproperty double x\n", b"0.5 9 9\n"))
    assert fields["x"].tolist() == [0.5] and fields["x"].dtype == np.float64


# PLY type name -> (struct code, a value that only that type holds exactly)
_TYPES = {
    "char": ("b", -100), "int8": ("b", -7), "uchar": ("B", 200), "uint8": ("B", 255), "short": ("h", -30000),
    "int16": ("h", 1234), "ushort": ("H", 60000), "uint16": ("H", 65535), "int": ("i", -2_000_000_000),
    "int32": ("i", 7), "uint": ("I", 4_000_000_000), "uint32": ("I", 3), "float": ("f", 0.1), "float32": ("f", -2.5),
    "double": ("d", 0.1), "float64": ("d", 1e300),
}


def _ply(path, fmt: str, props: dict[str, tuple[str, str, object]], rows: int, extra_header: str = "") -> None:
    """A PLY written independently of the library: header text and packed records (or ASCII rows)."""
    head = f"ply\nformat {fmt} 1.0\ncomment made by hand\nobj_info scanner 7\nelement vertex {rows}\n"
    head += "".join(f"property {t} {n}\n" for n, (t, _, _) in props.items()) + extra_header + "end_header\n"
    if fmt == "ascii":
        body = "".join(" ".join(repr(v) for _, _, v in props.values()) + "\n" for _ in range(rows)).encode()
    else:
        order = "<" if fmt == "binary_little_endian" else ">"
        code = order + "".join(c for _, c, _ in props.values())
        body = b"".join(struct.pack(code, *(v for _, _, v in props.values())) for _ in range(rows))
    path.write_bytes(head.encode() + body)


@pytest.mark.parametrize("fmt", ["binary_little_endian", "binary_big_endian", "ascii"])
def test_every_ply_type_reads_its_value_and_dtype_in_native_byte_order(tmp_path, fmt):
    props = {f"p_{t}": (t, c, v) for t, (c, v) in _TYPES.items()}
    _ply(tmp_path / "a.ply", fmt, props, rows=2)
    fields, comments = read_ply(tmp_path / "a.ply")
    assert comments == ["made by hand", "scanner 7"]
    assert list(fields) == list(props)
    for name, (t, code, v) in props.items():
        want = np.array([v, v], dtype=np.dtype(code))  # struct code == numpy code of that width
        assert fields[name].dtype == want.dtype, name
        assert fields[name].dtype.byteorder in ("=", "|"), name
        np.testing.assert_array_equal(fields[name], want, err_msg=name)
    assert bb.ply_field_names(tmp_path / "a.ply") == list(props)


def test_ply_elements_after_vertex_are_skipped_blank_lines_allowed_and_empty_vertices_read(tmp_path):
    props = {"x": ("float", "f", 1.5), "y": ("double", "d", -2.0)}
    _ply(tmp_path / "a.ply", "binary_little_endian", props, rows=3,
         extra_header="\nelement face 1\nproperty list uchar int vertex_indices\n")
    fields, _ = read_ply(tmp_path / "a.ply")
    assert fields["x"].tolist() == [1.5] * 3 and fields["y"].tolist() == [-2.0] * 3
    (tmp_path / "e.ply").write_bytes(HEAD + b"element vertex 0\nend_header\n")
    assert read_ply(tmp_path / "e.ply")[0] == {}


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


def test_write_ply_bytes_match_a_layout_by_hand(tmp_path):
    x = np.array([1.0, -2.0], np.float64)
    y = np.array([0.5, 0.25], np.float32)
    c = np.array([3, 250], np.uint8)
    s = np.array([-5, 7], np.int16)
    write_ply(tmp_path / "w.ply", {"x": x, "y": y.astype(np.float16), "c": c, "s": s}, ["hello"], comment_keyword="obj_info")
    raw = (tmp_path / "w.ply").read_bytes()
    head = (b"ply\nformat binary_little_endian 1.0\nobj_info hello\nelement vertex 2\nproperty double x\n"
            b"property float y\nproperty uchar c\nproperty short s\nend_header\n")
    body = b"".join(struct.pack("<dfBh", x[i], y[i], c[i], s[i]) for i in range(2))
    assert raw == head + body
    # comments: none by default, 'comment' lines unless another keyword is given
    plain = write_ply(tmp_path / "a.ply", {"x": np.arange(3, dtype=np.float32)}).read_bytes()
    assert plain.startswith(b"ply\nformat binary_little_endian 1.0\nelement vertex 3\nproperty float x\nend_header\n")
    noted = write_ply(tmp_path / "b.ply", {"x": np.arange(3, dtype=np.float32)}, ["made by hand"]).read_bytes()
    assert noted.startswith(b"ply\nformat binary_little_endian 1.0\ncomment made by hand\nelement vertex 3\n")
    with pytest.raises(FileFormatError, match="write_ply: fields must be 1-D arrays of one length"):
        write_ply(tmp_path / "bad.ply", {"a": np.zeros(2), "b": np.zeros(3)})
    with pytest.raises(FileFormatError, match="write_ply"):
        write_ply(tmp_path / "bad.ply", {"a": np.zeros((2, 2))})


def test_ply_columns_take_every_numbered_field_in_order():
    fields = {"f_0": np.array([1.0, 2.0]), "f_2": np.array([5.0, 6.0]), "f_1": np.array([3.0, 4.0]),
              "f_rest": np.array([9.0, 9.0]), "x": np.zeros(2)}
    got = ply_columns(fields, "f_", source="a.ply")
    assert got.dtype == np.float32 and got.tolist() == [[1.0, 3.0, 5.0], [2.0, 4.0, 6.0]]
    assert ply_columns(fields, "f_", source="a.ply", count=2).tolist() == [[1.0, 3.0], [2.0, 4.0]]
    with pytest.raises(FileFormatError, match=r"^a\.ply: PLY fields f_\* .*\(missing f_1\)$"):
        ply_columns({"f_0": fields["f_0"], "f_2": fields["f_2"]}, "f_", source="a.ply")
    with pytest.raises(FileFormatError, match=r"a.ply: PLY fields f_\* are not numbered 0..n-1 \(a number used twice\)"):
        ply_columns({"f_0": fields["f_0"], "f_00": fields["f_0"]}, "f_", source="a.ply")
    with pytest.raises(FileFormatError, match=r"a.ply: missing PLY field\(s\) \['f_3'\]"):
        ply_columns(fields, "f_", source="a.ply", count=4)
    with pytest.raises(FileFormatError, match=r"a.ply: missing PLY field\(s\) \['g_0'\]"):
        ply_columns(fields, "g_", source="a.ply", count=0)
    with pytest.raises(FileFormatError, match=r"a.ply: missing PLY field\(s\) \['x', 'z'\]"):
        bb.require_fields({"y": fields["f_0"]}, ["x", "y", "z"], source="a.ply")
    xyz = bb.ply_xyz({"x": np.array([1.0]), "y": np.array([2.0]), "z": np.array([3.0])})
    assert xyz.tolist() == [[1.0, 2.0, 3.0]] and xyz.dtype == np.float32


def test_ply_offsets_layout_by_hand():
    # K = 2 offsets: f_offset_{c*K + k} is coordinate c of offset k, so vertex 0's offsets are
    # k=0: (f0, f2, f4) and k=1: (f1, f3, f5)
    fields = {f"f_offset_{i}": np.array([float(i), 10.0 + i]) for i in range(6)}
    got = bb.ply_offsets(fields, 2, source="s")
    assert got.shape == (2, 2, 3) and got.dtype == np.float32
    assert got[0].tolist() == [[0.0, 2.0, 4.0], [1.0, 3.0, 5.0]]
    assert got[1].tolist() == [[10.0, 12.0, 14.0], [11.0, 13.0, 15.0]]
    assert got.flags["C_CONTIGUOUS"]
    with pytest.raises(FileFormatError, match="s: expected 6 f_offset_\\* fields \\(3 x n_offsets=2\\), got 3"):
        bb.ply_offsets({f"f_offset_{i}": fields["f_offset_0"] for i in range(3)}, 2, source="s")


# ----------------------------------------------------------------------------------------- cfg_args
def test_cfg_args_values_come_back_as_written():
    got = parse_cfg_args("Namespace(a=inf, b=-inf, c=nan, d=-3, e=1e-3, f='x', g=[1, (2, 3)], h={'k': None}, "
                         "i=True, j=-0.5, source_path='/d/x', test_iterations=[7000, 30000])\n")
    assert got["a"] == math.inf and got["b"] == -math.inf and math.isnan(got["c"])
    assert got["d"] == -3 and got["e"] == 0.001 and got["f"] == "x" and got["g"] == [1, (2, 3)]
    assert got["h"] == {"k": None} and got["i"] is True and got["j"] == -0.5
    assert got["source_path"] == "/d/x" and got["test_iterations"] == [7000, 30000]
    assert list(got) == [*"abcdefghij", "source_path", "test_iterations"]


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


def test_cfg_value_by_hand():
    assert cfg_value("0.5", float, key="k", source="s") == 0.5
    assert cfg_value(True, bool, key="k", source="s") is True
    assert cfg_value("false", bool, key="k", source="s") is False
    with pytest.raises(FileFormatError, match=r"^s: k=True must be a number"):
        cfg_value(True, int, key="k", source="s")
    with pytest.raises(FileFormatError, match=r"^s: k=3 must be at least 4"):
        cfg_value(3, int, key="k", source="s", low=4)


#: (id, cfg_args text, what the refusal names besides the source); nothing in them is ever run
CFG_REFUSALS = [
    ("call", "Namespace(a=os.system('x'))", "value of 'a' must be a Python literal"),
    ("call after a literal", "Namespace(a=1, weird=os.system('x'))", "value of 'weird' must be a Python literal"),
    ("name", "Namespace(a=foo)", "value of 'a'"),
    ("infinity", "Namespace(a=infinity)", "value of 'a'"),
    ("attribute", "Namespace(a=os.path)", "value of 'a'"),
    ("lambda", "Namespace(a=lambda: 1)", "value of 'a'"),
    ("set of lists", "Namespace(a={[1]})", "value of 'a'"),
    ("100k terms", "Namespace(a=" + "+".join(["1"] * 100_000) + ")", "not a printed argparse Namespace"),
    ("deep list", "Namespace(a=" + "[" * 500 + "]" * 500 + ")", "not a printed argparse Namespace"),
    ("deep list 40", "Namespace(a=" + "[" * 40 + "]" * 40 + ")", "nested deeper than 32 levels"),
    ("not a Namespace", "Other(a=1)", "expected 'Namespace(...)', got 'Other(a=1)'"),
    ("a call", "__import__('os')", "expected 'Namespace(...)'"),
    ("syntax error", "Namespace(a=", "not a printed argparse Namespace"),
    ("positional", "Namespace(1, a=2)", "positional arguments"),
    ("double star", "Namespace(**d)", "'**'"),
    ("empty", "", "not a printed argparse Namespace"),
]


@pytest.mark.parametrize("text, words", [c[1:] for c in CFG_REFUSALS], ids=[c[0] for c in CFG_REFUSALS])
def test_cfg_args_refusals_name_the_source_and_the_problem(tmp_path, text, words):
    p = tmp_path / "cfg_args"
    p.write_text(text)
    with pytest.raises(FileFormatError) as e:
        read_cfg_args(p)
    assert str(e.value).startswith(f"{p}: ") and words in str(e.value), str(e.value)
    with pytest.raises(FileFormatError, match="^model/cfg_args: ") as e:
        parse_cfg_args(text, source="model/cfg_args")
    assert words in str(e.value)
    with pytest.raises(FileFormatError, match="^cfg_args: "):  # the default source
        parse_cfg_args(text)


def test_cfg_args_bounds_are_32_levels_100000_terms_and_1_mib(tmp_path):
    # Namespace(a=[[...]]) with n lists: Call (depth 0), keyword (1), lists (2 .. n + 1), the innermost
    # list's Load (n + 2); the reader allows depth <= 32 + 2, so n = 32 is read and n = 33 refused
    def nested(n: int) -> str:
        return "Namespace(a=" + "[" * n + "]" * n + ")"

    got = parse_cfg_args(nested(32))["a"]
    for _ in range(31):
        got = got[0]
    assert got == []
    with pytest.raises(FileFormatError, match=r"^cfg_args: nested deeper than 32 levels or longer than 100000 terms"):
        parse_cfg_args(nested(33))
    # Namespace(a=[0, ..., 0]) with k zeros: Call, Name, Load, keyword, List, Load and k Constants = k + 6 nodes
    k = 100_000 - 6
    text = f"Namespace(a=[{', '.join(['0'] * k)}])"
    assert sum(1 for _ in ast.walk(ast.parse(text, mode="eval").body)) == 100_000  # brute-force count
    assert parse_cfg_args(text, source="big")["a"] == [0] * k
    with pytest.raises(FileFormatError, match=r"^over: nested deeper than 32 levels or longer than 100000 terms"):
        parse_cfg_args(f"Namespace(a=[{', '.join(['0'] * (k + 1))}])", source="over")  # one node more
    # text and files of up to 1 MiB
    pad = " " * (MIB - len("Namespace(a=1)"))
    assert parse_cfg_args("Namespace(a=1)" + pad) == {"a": 1}
    with pytest.raises(FileFormatError, match=r"^src: 1048577 characters, more than a cfg_args holds \(<= 1048576\)"):
        parse_cfg_args("Namespace(a=1)" + pad + " ", source="src")
    p = tmp_path / "cfg_args"
    p.write_text("Namespace(a=1)" + pad)
    assert read_cfg_args(p) == {"a": 1}
    p.write_text("Namespace(a=1)" + pad + " ")
    with pytest.raises(FileFormatError, match=rf"{p}: 1048577 bytes, more than a cfg_args holds \(<= 1048576\)"):
        read_cfg_args(p)
    with pytest.raises(FileFormatError, match="missing_cfg: no such file"):
        read_cfg_args(tmp_path / "missing_cfg")


# --------------------------------------------------------------------------------------------- YAML
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
        "  tag: v1#2\n"
        "  colour: '#ff0000'\n"
        "#whole: 1\n"
        "flow: {\n"
        "  feat_dim: 50,\n"
        "}\n")
    got = read_yaml_scalars(tmp_path / "c.yaml")
    assert got["feat_dim"] == [32, 50] and isinstance(got["feat_dim"][0], int)
    assert got["voxel_size"] == [0.001] and got["name"] == ["octree: x"] and got["other"] == ["q"]
    assert got["on"] == [True] and got["off"] == [False] and got["nothing"] == [None] and got["none2"] == [None]
    assert got["iters"] == [40000] and got["word"] == ["plain text"]
    assert got["tag"] == ["v1#2"] and got["colour"] == ["#ff0000"]  # a '#' inside a value is not a comment
    assert not {"nested", "items", "model", "flow", "whole"} & set(got)


def test_yaml_scalars_survive_bytes_that_are_not_utf8(tmp_path):
    """Octree-AnyGS configs are read as text with undecodable bytes replaced (a Latin-1 comment or
    path), not refused with a UnicodeDecodeError."""
    path = tmp_path / "config.yaml"
    path.write_bytes(b"# caf\xe9 scene\nmodel:\n  voxel_size: 0.01  # m\xe9tres\n  name: sc\xe8ne\n")
    assert read_yaml_scalars(path) == {"voxel_size": [0.01], "name": ["sc\ufffdne"]}


def test_yaml_bound_is_1_mib_and_a_missing_file_is_named(tmp_path):
    y = tmp_path / "c.yaml"
    y.write_text("a: 1\n" + "#" * (MIB - 6) + "\n")
    assert read_yaml_scalars(y) == {"a": [1]}
    y.write_text("a: 1\n" + "#" * (MIB - 5) + "\n")
    with pytest.raises(FileFormatError, match=r"c\.yaml: 1048577 bytes, more than a config file holds \(<= 1048576\)"):
        read_yaml_scalars(y)
    with pytest.raises(FileFormatError, match="no.yaml: no such file"):
        read_yaml_scalars(tmp_path / "no.yaml")


# -------------------------------------------------------------------------------------- state dicts
class _Evil:
    def __reduce__(self):
        return (os.system, ("true",))


@pytest.mark.filterwarnings("ignore:Detected pickle protocol")
@pytest.mark.parametrize("kind, words", [("pickle", "checkpoint.pth"), ("path object", "checkpoint.pth"),
                                         ("list", "expected a dict of state dicts, got list"), ("garbage", "checkpoint.pth"),
                                         ("truncated", "checkpoint.pth"), ("missing", "no such file")])
def test_state_dict_files_are_read_weights_only(tmp_path, kind, words):
    good = tmp_path / "ok.pth"
    torch.save({"opacity_mlp": {"0.weight": torch.ones(2, 2)}}, good)
    assert torch.equal(load_state_dict_file(good)["opacity_mlp"]["0.weight"], torch.ones(2, 2))
    p = tmp_path / "checkpoint.pth"
    if kind == "pickle":
        torch.save({"m": _Evil()}, p)
    elif kind == "path object":
        torch.save({"x": Path("/etc")}, p)  # a pickled non-tensor object
    elif kind == "list":
        torch.save([torch.zeros(1)], p)
    elif kind == "garbage":
        p.write_bytes(b"\x80\x04not a torch file")
    elif kind == "truncated":
        p.write_bytes(good.read_bytes()[:50])
    with pytest.raises(FileFormatError, match="checkpoint.pth") as e:
        load_state_dict_file(p)
    assert words in str(e.value)


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


# ------------------------------------------------------------------------------- TorchScript decoders
def test_appearance_embedding_tensors_are_read_as_data_or_trusted(tmp_path):
    path = tmp_path / "embedding_appearance.pt"
    torch.jit.trace(Embedding(7, 32), torch.zeros(3, dtype=torch.long)).save(str(path))
    got = load_torchscript_tensors(path)
    want = _trusted(path).state_dict()
    assert got.keys() == want.keys() == {"embedding.weight"} and torch.equal(got["embedding.weight"], want["embedding.weight"])
    trusted = load_torchscript_tensors(path, trust_code=True)
    assert torch.equal(trusted["embedding.weight"], want["embedding.weight"])


def test_trust_code_is_an_explicit_opt_in_never_a_fallback(tmp_path):
    class Sequential(nn.Sequential):  # outside the safe subset (a class of its own), harmless
        @torch.jit.export
        def extra(self) -> int:
            return 1

    dec = Sequential(nn.Linear(4, 4), nn.ReLU())
    path = tmp_path / "opacity_mlp.pt"
    torch.jit.script(dec).save(str(path))
    with pytest.raises(FileFormatError, match="opacity_mlp.pt"):
        load_torchscript(path)  # the default never falls back to torch.jit.load
    x = torch.randn(3, 4)
    assert torch.equal(load_torchscript(path, trust_code=True)(x), dec(x))
    good = tmp_path / "ok.pth"
    torch.save({"opacity_mlp": {"0.weight": torch.ones(2, 2)}}, good)
    with pytest.raises(FileFormatError, match="ok.pth: .*TorchScript"):
        load_torchscript(good)  # a state dict is not a TorchScript archive


def test_trusted_torchscript_paths_name_the_file(tmp_path):
    """``trust_code=True`` on archives this test wrote itself (the opt-in path: ``torch.jit.load``)."""
    with pytest.raises(FileFormatError, match=r"gone\.pt: no such file"):
        load_torchscript(tmp_path / "gone.pt", trust_code=True)
    with pytest.raises(FileFormatError, match=r"gone\.pt: no such file"):
        load_torchscript_tensors(tmp_path / "gone.pt", trust_code=True)
    (tmp_path / "junk.pt").write_bytes(b"not a zip at all")
    with pytest.raises(FileFormatError, match=r"junk\.pt: not a loadable TorchScript archive \(truncated\?\)"):
        load_torchscript(tmp_path / "junk.pt", trust_code=True)
    # without trust_code the same files are refused by the data reader, never returned as None
    with pytest.raises(FileFormatError, match=r"gone\.pt: no such file"):
        tensors_from_archive(tmp_path / "gone.pt")
    with pytest.raises(FileFormatError, match=r"junk\.pt: not a TorchScript archive \(not a zip file"):
        tensors_from_archive(tmp_path / "junk.pt")
    torch.jit.save(torch.jit.script(nn.Sequential(nn.Linear(3, 2), nn.GELU())), str(tmp_path / "gelu.pt"))
    lin = nn.Sequential(nn.Linear(3, 2), nn.Sigmoid())
    torch.jit.save(torch.jit.trace(lin, torch.randn(2, 3)), str(tmp_path / "ok.pt"))
    with pytest.raises(FileFormatError, match=r"gelu\.pt: TorchScript decoder cannot be rebuilt as an eager module: .*GELU"):
        load_torchscript(tmp_path / "gelu.pt", trust_code=True)
    got = load_torchscript(tmp_path / "ok.pt", trust_code=True)
    x = torch.randn(4, 3)
    assert not isinstance(got, torch.jit.ScriptModule) and torch.equal(got(x), lin(x))
    sd = load_torchscript_tensors(tmp_path / "ok.pt", trust_code=True)
    assert list(sd) == ["0.weight", "0.bias"] and torch.equal(sd["0.weight"], lin[0].weight)
    assert not sd["0.weight"].requires_grad
