"""File formats checked against files written by hand (struct/json, not the library's writers),
and every refusal of the readers triggered: error type and the file/field named."""

from __future__ import annotations

import json
import math
import os
import struct
import subprocess
import sys
import warnings

import numpy as np
import pytest
import torch
from safetensors.torch import save_file

from controlgs_adapter.errors import FileFormatError, InputValueError, NonFiniteError
from controlgs_adapter.formats import backbone as bb
from controlgs_adapter.formats import layout
from controlgs_adapter.formats import safetensors as st

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


def _header(tmp_path, lines: str, body: bytes = b""):
    p = tmp_path / "h.ply"
    p.write_bytes(b"ply\n" + lines.encode() + b"end_header\n" + body)
    return p


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


# --- cfg_args


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


# --- YAML scalars


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


# --- PLY columns


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


# --- safetensors container


def _raw(path, header: object | None, extra_meta: dict | None = None) -> None:
    meta = {} if header is None else {st.HEADER_KEY: header if isinstance(header, str) else json.dumps(header)}
    save_file({"t": torch.zeros(2)}, str(path), metadata={**meta, **(extra_meta or {})})


@pytest.mark.parametrize("header, words", [
    (None, "not written by controlgs-adapter"),
    ("{not json", "corrupt controlgs-adapter header: JSONDecodeError"),
    ([1, 2], "header must be a JSON object, got list"),
    ({"kind": "psf_bank", "format_version": 1}, "holds a 'psf_bank', expected a 'adapter'"),
    ({"format_version": 1}, "holds a None, expected a 'adapter'"),
    ({"kind": "adapter", "format_version": True}, "format_version must be an integer >= 1, got True"),
    ({"kind": "adapter", "format_version": 0}, "format_version must be an integer >= 1, got 0"),
    ({"kind": "adapter", "format_version": "1"}, "format_version must be an integer >= 1, got '1'"),
    ({"kind": "adapter", "format_version": 1.0}, "format_version must be an integer >= 1, got 1.0"),
    ({"kind": "adapter", "format_version": 3, "library_version": "9.9"},
     "format_version 3 is newer than this library reads (<= 2); written by controlgs-adapter 9.9"),
])
def test_read_header_refusals(tmp_path, header, words):
    _raw(tmp_path / "f.safetensors", header)
    with pytest.raises(FileFormatError, match="f.safetensors: ") as e:
        st.read_header(tmp_path / "f.safetensors", kind="adapter", max_version=2)
    assert words in str(e.value)


def test_read_header_accepts_versions_up_to_max_and_load_tensors_reads_data(tmp_path):
    for v in (1, 2):
        _raw(tmp_path / "f.safetensors", {"kind": "adapter", "format_version": v, "x": [1]})
        assert st.read_header(tmp_path / "f.safetensors", kind="adapter", max_version=2)["x"] == [1]
    tensors, header = st.load_tensors(tmp_path / "f.safetensors", kind="adapter", max_version=2)
    assert list(tensors) == ["t"] and tensors["t"].tolist() == [0.0, 0.0] and header["format_version"] == 2
    with pytest.raises(FileFormatError, match="nope.safetensors: no such file"):
        st.read_header(tmp_path / "nope.safetensors", kind="adapter", max_version=2)
    (tmp_path / "junk.safetensors").write_bytes(b"\x08\0\0\0\0\0\0\0{}")
    with pytest.raises(FileFormatError, match="junk.safetensors: not a readable safetensors file"):
        st.read_header(tmp_path / "junk.safetensors", kind="adapter", max_version=2)


def test_save_tensors_header_and_data_read_back_by_safetensors_itself(tmp_path):
    from safetensors import safe_open

    a = torch.arange(6.0).view(2, 3).t()  # non-contiguous
    st.save_tensors(tmp_path / "s.safetensors", {"a": a, "b": a[0]}, {"extra": 5}, kind="k1", format_version=4)
    with safe_open(str(tmp_path / "s.safetensors"), framework="pt") as f:
        meta = f.metadata()
        assert torch.equal(f.get_tensor("a"), a) and torch.equal(f.get_tensor("b"), a[0])
    h = json.loads(meta[st.HEADER_KEY])
    from controlgs_adapter._version import __version__
    assert h == {"kind": "k1", "format_version": 4, "library_version": __version__, "extra": 5}
    assert meta["format"] == "pt"
    assert oct((tmp_path / "s.safetensors").stat().st_mode & 0o777) == oct(st.file_mode())


def test_save_tensors_refusals_write_nothing(tmp_path):
    p = tmp_path / "s.safetensors"
    with pytest.raises(NonFiniteError, match=r"s.safetensors: refusing to save tensor 'w': it holds 2 NaN/Inf value\(s\)$"):
        st.save_tensors(p, {"w": torch.tensor([1.0, math.nan, math.inf])}, {}, kind="k", format_version=1)
    with pytest.raises(NonFiniteError, match="overflowed"):
        st.save_tensors(p, {"h": torch.tensor([1e6]).half()}, {}, kind="k", format_version=1)
    with pytest.raises(NonFiniteError, match="s.safetensors: refusing to save a header with a NaN/Inf number"):
        st.save_tensors(p, {}, {"x": math.nan}, kind="k", format_version=1)
    with pytest.raises(InputValueError, match="s.safetensors: tensor 'n' must be a torch.Tensor, got ndarray"):
        st.save_tensors(p, {"n": np.zeros(2)}, {}, kind="k", format_version=1)  # type: ignore[dict-item]
    assert list(tmp_path.iterdir()) == []
    st.save_tensors(p, {"i": torch.tensor([2**31 - 1], dtype=torch.int32)}, {}, kind="k", format_version=1)  # ints pass
    with pytest.raises(InputValueError, match="path must be a file path"):
        st.save_tensors("", {}, {}, kind="k", format_version=1)


def test_remove_stale_tmp_only_removes_dead_writers(tmp_path):
    target = tmp_path / "a.safetensors"
    dead = subprocess.run([sys.executable, "-c", "import os; print(os.getpid())"], capture_output=True, text=True,
                          check=True).stdout.strip()
    stale = tmp_path / f".a.safetensors.{dead}.xyz.tmp"
    mine = tmp_path / f".a.safetensors.{os.getpid()}.abc.tmp"
    alive = tmp_path / f".a.safetensors.{os.getppid()}.def.tmp"
    other = tmp_path / f".b.safetensors.{dead}.xyz.tmp"
    odd = tmp_path / ".a.safetensors.notapid.tmp"
    for p in (stale, mine, alive, other, odd):
        p.write_bytes(b"x")
    assert st.remove_stale_tmp(target) == [stale]
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted(p.name for p in (mine, alive, other, odd))


def test_atomic_write_leaves_no_tmp_on_failure_and_refuses_folders(tmp_path):
    from controlgs_adapter.errors import FileWriteError

    def fail(tmp: str) -> None:
        open(tmp, "wb").write(b"half")
        raise OSError(28, "No space left on device")

    with pytest.raises(FileWriteError, match="x.bin: write failed: No space left on device"):
        st.atomic_write(tmp_path / "x.bin", fail)
    assert list(tmp_path.iterdir()) == []

    def boom(tmp: str) -> None:
        raise KeyError("k")

    with pytest.raises(KeyError):
        st.atomic_write(tmp_path / "x.bin", boom)
    assert list(tmp_path.iterdir()) == []
    (tmp_path / "d").mkdir()
    with pytest.raises(InputValueError, match="d: is a folder"):
        st.atomic_write(tmp_path / "d", fail)
    (tmp_path / "file").write_bytes(b"")
    with pytest.raises(FileWriteError, match="cannot write here"):
        st.atomic_write(tmp_path / "file" / "sub" / "x.bin", fail)
    out = st.atomic_write(str(tmp_path / "new" / "y.bin"), lambda tmp: open(tmp, "wb").write(b"ok"))
    assert out == tmp_path / "new" / "y.bin" and out.read_bytes() == b"ok"
    assert st.as_path(os.fsencode(str(out))) == out


# --- layout


def test_iteration_dir_choices_and_refusals(tmp_path):
    with pytest.raises(FileFormatError, match=r"no 'point_cloud/iteration_<N>' folder\)$"):
        layout.iteration_dir(tmp_path, None, family="Fam")
    (tmp_path / "bitstreams").mkdir()
    with pytest.raises(FileFormatError, match="not a Fam output directory.*bitstreams/ was found"):
        layout.iteration_dir(tmp_path, None, family="Fam")
    pc = tmp_path / "point_cloud"
    pc.mkdir()
    with pytest.raises(FileFormatError, match="point_cloud: no 'iteration_<N>' folder .*bitstreams/ was found"):
        layout.iteration_dir(tmp_path, None, family="Fam")
    for n in (7, 30000, 500):
        (pc / f"iteration_{n}").mkdir()
    (pc / "iteration_99999.bak").mkdir()
    (pc / "iteration_123456").write_bytes(b"")  # a file, not a folder
    assert layout.iteration_dirs(tmp_path) == {7: pc / "iteration_7", 30000: pc / "iteration_30000", 500: pc / "iteration_500"}
    assert layout.iteration_dir(tmp_path, None, family="Fam") == pc / "iteration_30000"
    assert layout.iteration_dir(tmp_path, 7, family="Fam") == pc / "iteration_7"
    with pytest.raises(FileFormatError, match=r"point_cloud: no 'iteration_8' folder \(present: \[7, 500, 30000\]\)"):
        layout.iteration_dir(tmp_path, 8, family="Fam")
    assert layout.bitstreams_only(tmp_path / "point_cloud") == ""


# --- training checkpoint (controlgs_adapter.formats.checkpoint), files built by hand


def _ckpt(**over):
    from controlgs_adapter.formats.checkpoint import Checkpoint

    base = dict(adapter={"conditions": torch.full((3, 1, 2), 0.5), "projections.lens.d4.weight": torch.ones(4, 2)},
                optimizer_state={0: {"step": 3.0, "exp_avg": torch.full((3, 1, 2), 0.1), "exp_avg_sq": torch.zeros(3, 1, 2)},
                                 1: {"step": torch.tensor(3.0), "exp_avg": torch.ones(4, 2), "exp_avg_sq": torch.ones(4, 2)}},
                param_groups=[{"lr": 0.01, "params": [0, 1]}], rng=torch.arange(8, dtype=torch.uint8), iteration=3,
                history=[1.0, 0.5, 0.25], config={"lr": 0.01, "iterations": 10, "checkpoint_every": 5, "loss": {"l1": 1.0}},
                modules=["lens"], effects=["lens"], fingerprint="fp", data="views")
    return Checkpoint(**{**base, **over})


_SHAPES = [torch.Size([3, 1, 2]), torch.Size([4, 2])]


def _raw_ckpt(path, tensors, header):
    from controlgs_adapter.formats.checkpoint import CHECKPOINT_KIND

    h = {"kind": CHECKPOINT_KIND, "format_version": 1, **header}
    save_file(tensors, str(path), metadata={st.HEADER_KEY: json.dumps(h)})


def test_checkpoint_round_trip_and_tensor_names(tmp_path):
    from controlgs_adapter.formats.checkpoint import read_checkpoint, write_checkpoint

    c = _ckpt()
    p = write_checkpoint(tmp_path / "c.safetensors", c)
    with __import__("safetensors").safe_open(str(p), framework="pt") as f:
        names = sorted(f.keys())
        assert f.get_tensor("optimizer.0.step").shape == () and float(f.get_tensor("optimizer.0.step")) == 3.0
    assert names == sorted(["adapter.conditions", "adapter.projections.lens.d4.weight", "rng"]
                           + [f"optimizer.{i}.{k}" for i in (0, 1) for k in ("step", "exp_avg", "exp_avg_sq")])
    # a resumed run may change iterations and checkpoint_every only
    like = _ckpt(config={**c.config, "iterations": 99, "checkpoint_every": 1})
    back = read_checkpoint(p, like, _SHAPES)
    assert back.iteration == 3 and back.history == [1.0, 0.5, 0.25] and back.config == c.config
    assert torch.equal(back.adapter["conditions"], c.adapter["conditions"]) and torch.equal(back.rng, c.rng)
    assert torch.equal(back.optimizer_state[1]["exp_avg"], torch.ones(4, 2)) and back.param_groups == c.param_groups
    assert (back.modules, back.effects, back.fingerprint, back.data) == (["lens"], ["lens"], "fp", "views")


@pytest.mark.parametrize("like, words", [
    (dict(config={"lr": 0.02, "iterations": 10, "checkpoint_every": 5, "loss": {"l1": 1.0}}), "different config (lr)"),
    (dict(config={"lr": 0.01, "iterations": 10, "checkpoint_every": 5, "loss": {"l1": 2.0}}), "different config (loss)"),
    (dict(effects=["lens", "oled"]), "stages ['lens'], this trainer's are ['lens', 'oled']"),
    (dict(fingerprint="other"), "another backbone"),
    (dict(data="other"), "other views (data views)"),
    (dict(modules=["lens", "display"]), "trains modules ['lens'], this trainer ['lens', 'display']"),
    (dict(rng=torch.arange(9, dtype=torch.uint8)), "'rng' must be a torch.uint8 tensor of shape [9], got torch.uint8 [8]"),
    (dict(rng=torch.arange(8, dtype=torch.int64)), "'rng' must be a torch.int64 tensor of shape [8], got torch.uint8 [8]"),
    (dict(param_groups=[{"lr": 0.01, "params": [0]}, {"lr": 0.01, "params": [1]}]), "'param_groups' does not describe"),
    (dict(param_groups=[{"lr": 0.01, "params": [1, 0]}]), "'param_groups' does not describe"),
    (dict(adapter={"conditions": torch.zeros(3, 1, 3), "projections.lens.d4.weight": torch.ones(4, 2)}),
     "do not fit this adapter (missing, unexpected or mis-shaped: ['conditions'])"),
    (dict(adapter={"conditions": torch.zeros(3, 1, 2)}), "mis-shaped: ['projections.lens.d4.weight']"),
])
def test_checkpoint_of_another_run_is_refused(tmp_path, like, words):
    from controlgs_adapter.formats.checkpoint import read_checkpoint, write_checkpoint

    p = write_checkpoint(tmp_path / "c.safetensors", _ckpt())
    with pytest.raises(FileFormatError, match="c.safetensors: ") as e:
        read_checkpoint(p, _ckpt(**like), _SHAPES)
    assert words in str(e.value)


@pytest.mark.parametrize("edit, words", [
    (lambda t, h: t.update({"adapter.conditions": torch.full((3, 1, 2), math.nan)}), "['adapter.conditions'] hold NaN/Inf"),
    (lambda t, h: t.update({"optimizer.2.step": torch.tensor(1.0)}), "'optimizer.2.step' ([]) is not Adam state of this adapter's 2"),
    (lambda t, h: t.update({"optimizer.x.step": torch.tensor(1.0)}), "'optimizer.x.step'"),
    (lambda t, h: t.update({"optimizer.0.momentum": torch.zeros(3, 1, 2)}), "'optimizer.0.momentum'"),
    (lambda t, h: t.update({"optimizer.1.exp_avg": torch.zeros(2, 4)}), "'optimizer.1.exp_avg' ([2, 4])"),
    (lambda t, h: t.update({"extra": torch.zeros(1)}), "unexpected tensors ['extra']"),
    (lambda t, h: t.pop("rng"), "'rng' must be a torch.uint8 tensor of shape [8], got none"),
    (lambda t, h: h.update(iteration=-1), "'iteration' must be an integer >= 0, got -1"),
    (lambda t, h: h.update(iteration=True), "'iteration' must be an integer >= 0, got True"),
    (lambda t, h: h.update(iteration=2.0), "'iteration' must be an integer >= 0, got 2.0"),
    (lambda t, h: h.update(history=[1.0, math.inf]), "'history' must be a list of finite losses"),
    (lambda t, h: h.update(history=[True]), "'history' must be a list of finite losses"),
    (lambda t, h: h.update(history={"a": 1}), "'history' must be a list of finite losses"),
    (lambda t, h: h.update(param_groups={"params": [0, 1]}), "'param_groups' does not describe"),
    (lambda t, h: h.update(config=[1]), "'config' must be an object with a 'loss' object"),
    (lambda t, h: h.update(config={"lr": 0.01, "loss": 1}), "'config' must be an object with a 'loss' object"),
])
def test_checkpoint_malformed_files_are_refused(tmp_path, edit, words):
    from controlgs_adapter.formats.checkpoint import read_checkpoint

    c = _ckpt()
    tensors, header = c.tensors(), c.header()
    edit(tensors, header)
    _raw_ckpt(tmp_path / "c.safetensors", tensors, header)
    with pytest.raises(FileFormatError, match="c.safetensors: ") as e:
        read_checkpoint(tmp_path / "c.safetensors", c, _SHAPES)
    assert words in str(e.value)


def test_checkpoint_step_of_any_shape_and_missing_history_accepted(tmp_path):
    from controlgs_adapter.formats.checkpoint import read_checkpoint

    c = _ckpt()
    tensors, header = c.tensors(), c.header()
    tensors["optimizer.1.step"] = torch.tensor([3.0])
    del header["history"]
    _raw_ckpt(tmp_path / "c.safetensors", tensors, header)
    back = read_checkpoint(tmp_path / "c.safetensors", c, _SHAPES)
    assert back.history == [] and back.optimizer_state[1]["step"].tolist() == [3.0]


# --- adapter file (controlgs_adapter.formats.adapter) pieces


def _spec(**over):
    base = {"backend": "b", "modules": ["lens", "display"], "cond_dim": 2, "schedules": {
        "lens": {"lo": 0, "hi": 1.5}, "display": {"lo": 0.0, "hi": 1}}, "state_blind": False,
        "targets": [{"decoder": "mlp_color", "in_features": 3, "out_features": 4},
                    {"decoder": "mlp_opacity", "in_features": 3, "out_features": 6},
                    {"decoder": "mlp_cov", "in_features": 3, "out_features": 4}],
        "num_anchors": 5, "rows_per_anchor": 1, "fingerprint": "f"}
    return {**base, **over}


@pytest.mark.parametrize("over, bad", [
    (dict(backend=1), ["backend"]), (dict(modules="lens"), ["modules"]), (dict(cond_dim=2.0), ["cond_dim"]),
    (dict(state_blind=None), ["state_blind"]), (dict(num_anchors="5"), ["num_anchors"]),
    (dict(rows_per_anchor=None), ["rows_per_anchor"]), (dict(fingerprint=3), ["fingerprint"]),
    (dict(schedules={"lens": {"lo": 0, "hi": 1}}), ["schedules.display"]),
    (dict(schedules={"lens": {"lo": 0, "hi": "1"}, "display": {"lo": 0, "hi": 1}}), ["schedules.lens"]),
    (dict(schedules={"lens": {"lo": 0, "hi": 1}, "display": [0, 1]}), ["schedules.display"]),
    (dict(targets=[{"decoder": "d", "in_features": 3, "out_features": 4}, {"decoder": "d", "in_features": 3}]),
     ["targets[1]"]),
    (dict(targets=[{"decoder": 1, "in_features": 3, "out_features": 4}]), ["targets[0]"]),
    (dict(targets=["d"]), ["targets[0]"]),
])
def test_adapter_header_fields_checked(over, bad):
    from controlgs_adapter.formats.adapter import check_header

    assert check_header("a.safetensors", _spec()) == _spec()
    with pytest.raises(FileFormatError, match=rf"^a.safetensors: adapter header is missing or has malformed field\(s\) "
                                              rf"{__import__('re').escape(str(bad))}$"):
        check_header("a.safetensors", _spec(**over))


def test_adapter_tensor_mismatches_by_hand():
    from controlgs_adapter.formats.adapter import tensor_mismatches

    spec = _spec()
    good = {"conditions": torch.zeros(5, 2, 2), **{f"projections.{m}.d{d}.weight": torch.zeros(d, 2)
                                                   for m in ("lens", "display") for d in (4, 6)}}
    assert tensor_mismatches(good, spec) == []
    bad = {**good, "conditions": torch.zeros(5, 2, 3), "projections.lens.d4.weight": torch.zeros(4, 2, dtype=torch.int32),
           "projections.display.d6.weight": torch.full((6, 2), math.inf), "junk": torch.zeros(1)}
    del bad["projections.lens.d6.weight"]
    got = tensor_mismatches(bad, spec)
    assert got == [
        ("tensors missing from the file: ['projections.lens.d6.weight']", frozenset({"projections.lens.d6.weight"})),
        ("unexpected tensors in the file: ['junk']", frozenset({"junk"})),
        ("tensor 'conditions': shape [5, 2, 3], expected [5, 2, 2]", frozenset({"conditions"})),
        ("tensor 'projections.display.d6.weight': contains NaN/Inf", frozenset({"projections.display.d6.weight"})),
        ("tensor 'projections.lens.d4.weight': dtype torch.int32, expected a floating-point type",
         frozenset({"projections.lens.d4.weight"})),
    ]


def test_adapter_fingerprint_and_condition_mapping_by_hand():
    from controlgs_adapter.formats.adapter import fingerprint_mismatch, map_conditions

    assert fingerprint_mismatch({"fingerprint": "abc"}, "abc") == []
    (msg, skip), = fingerprint_mismatch({"fingerprint": "abc"}, "xyz")
    assert "trained on backbone abc, this model is xyz" in msg and skip is None
    saved = torch.arange(6.0).view(3, 1, 2)
    gathered = map_conditions(saved, ("gather", torch.tensor([2, 0])), 2)
    assert gathered.tolist() == [[[4.0, 5.0]], [[0.0, 1.0]]]
    scattered = map_conditions(saved, ("scatter", torch.tensor([4, 1, 0])), 5)
    assert scattered.tolist() == [[[4.0, 5.0]], [[2.0, 3.0]], [[0.0, 0.0]], [[0.0, 0.0]], [[0.0, 1.0]]]


def test_write_adapter_dtype_choices(tmp_path):
    from controlgs_adapter.formats.adapter import read_spec, read_tensors, write_adapter

    t = {"conditions": torch.tensor([[[1.0, -70000.0]]]), "projections.lens.d4.weight": torch.ones(4, 2)}
    spec = _spec(modules=["lens"], num_anchors=1, schedules={"lens": {"lo": 0, "hi": 1}})
    with pytest.raises(InputValueError, match="dtype must be None, torch.float16 or torch.float32, got torch.float64"):
        write_adapter(tmp_path / "a.safetensors", t, spec, dtype=torch.float64)
    with pytest.raises(NonFiniteError, match=r"a.safetensors: conditions reach \|7e\+04\|, beyond float16's range \(65504\)"):
        write_adapter(tmp_path / "a.safetensors", t, spec, dtype=torch.float16)
    assert not (tmp_path / "a.safetensors").exists()
    t["conditions"] = torch.tensor([[[1.0, -65504.0]]])
    write_adapter(tmp_path / "a.safetensors", t, spec, dtype=torch.float16)
    assert read_spec(tmp_path / "a.safetensors")["condition_dtype"] == "float16"
    assert read_tensors(tmp_path / "a.safetensors")["conditions"].dtype == torch.float16
    write_adapter(tmp_path / "b.safetensors", {**t, "conditions": t["conditions"].double()}, spec)
    assert read_spec(tmp_path / "b.safetensors")["condition_dtype"] == "float64"
    write_adapter(tmp_path / "c.safetensors", {**t, "conditions": t["conditions"].double()}, spec, dtype=torch.float32)
    assert read_tensors(tmp_path / "c.safetensors")["conditions"].dtype == torch.float32
    write_adapter(tmp_path / "d.safetensors", {**t, "conditions": torch.zeros(0, 1, 2)}, {**spec, "num_anchors": 0},
                  dtype=torch.float16)


# --- decoders (controlgs_adapter.formats.decoders), state dicts built by hand


def _sd(*shapes: tuple[int, int], at: tuple[int, ...] | None = None, bias: bool = True) -> dict[str, torch.Tensor]:
    g = torch.Generator().manual_seed(1)
    out = {}
    for i, (o, n) in zip(at or range(0, 2 * len(shapes), 2), shapes):
        out[f"{i}.weight"] = torch.randn(o, n, generator=g)
        if bias:
            out[f"{i}.bias"] = torch.randn(o, generator=g)
    return out


def test_build_mlp_computes_the_family_decoders_by_hand():
    from controlgs_adapter.formats.decoders import build_mlp

    x = torch.randn(5, 3, dtype=torch.float64)
    sd = {k: v.double() for k, v in _sd((4, 3), (2, 4)).items()}
    h = torch.relu(x @ sd["0.weight"].T + sd["0.bias"])
    z = h @ sd["2.weight"].T + sd["2.bias"]
    for attr, want in [("mlp_opacity", torch.tanh(z)), ("mlp_color", torch.sigmoid(z)),
                       ("mlp_feature_bank", torch.softmax(z, dim=1))]:
        torch.testing.assert_close(build_mlp(attr, sd, name="n", source="s").double()(x), want, rtol=1e-12, atol=1e-12)
    cov = build_mlp("mlp_cov", sd, name="n", source="s").double()
    torch.testing.assert_close(cov(x), z, rtol=1e-12, atol=1e-12)  # cov: no activation after the last Linear
    nobias = build_mlp("mlp_cov", _sd((4, 3), (2, 4), bias=False), name="n", source="s")
    assert nobias[0].bias is None and nobias[2].bias is None


@pytest.mark.parametrize("state, words", [
    ([1, 2], "s: entry 'n' is not a state dict (got list)"),
    ({"weight": torch.zeros(2, 2)}, "s: entry 'n' holds no '<i>.weight' Linear weights (keys: ['weight'])"),
    (_sd((4, 3), (2, 4), at=(0, 1)), "s: 'n' has a Linear at index 1 where an activation was expected"),
    (_sd((4, 3), (2, 5)), "s: 'n' layer 2 weight [2, 5] does not take the previous width 4"),
    ({"0.weight": torch.zeros(4)}, "s: 'n' layer 0 weight [4] does not take the previous width None"),
    (_sd((4, 3), (2, 4), at=(0, 4)), "s: 'n' has no layer at index 2 (keys: "),
])
def test_mlp_from_state_dict_refusals(state, words):
    from controlgs_adapter.formats.decoders import build_mlp

    with pytest.raises(FileFormatError) as e:
        build_mlp("mlp_opacity", state, name="n", source="s")
    assert words in str(e.value)


def test_decoders_from_state_dicts_optional_embedding_and_first_width():
    from torch import nn

    from controlgs_adapter.formats.decoders import check_first_width, decoders_from_state_dicts, embedding_from_state

    sd = {"op": _sd((4, 3), (1, 4)), "cov": _sd((4, 3), (7, 4))}
    got = decoders_from_state_dicts(sd, {"mlp_opacity": "op", "mlp_cov": "cov", "mlp_color": "col"}, source="f.pth",
                                    optional=("mlp_color",))
    assert sorted(got) == ["mlp_cov", "mlp_opacity"] and isinstance(got["mlp_opacity"][3], nn.Tanh)
    with pytest.raises(FileFormatError, match=r"^f.pth: missing entry 'col' \(has \['cov', 'op'\]\)$"):
        decoders_from_state_dicts(sd, {"mlp_color": "col"}, source="f.pth")
    table = torch.arange(6.0).view(3, 2)
    emb = embedding_from_state({"embedding.weight": table.double()}, source="e")
    assert emb(torch.tensor([2, 0])).tolist() == [[4.0, 5.0], [0.0, 1.0]] and emb.weight.dtype == torch.float32
    assert not emb.weight.requires_grad
    for bad in ({}, {"a.weight": table, "b.weight": table}, {"weight": torch.zeros(3)}):
        with pytest.raises(FileFormatError, match=r"^e: expected one \[num_cameras, appearance_dim\] embedding table$"):
            embedding_from_state(bad, source="e")
    check_first_width(got["mlp_cov"], 3, name="mlp_cov", source="f", layout="L")
    with pytest.raises(FileFormatError, match=r"^f: mlp_cov takes 3 inputs, the configuration gives 5 \(L\)$"):
        check_first_width(got["mlp_cov"], 5, name="mlp_cov", source="f", layout="L")


def test_decoders_unite_file_modes_and_refusals(tmp_path):
    from controlgs_adapter.formats.decoders import Decoders

    with pytest.raises(FileFormatError, match=r"missing MLPs: neither the TorchScript traces \['opacity_mlp.pt', "
                                              r"'cov_mlp.pt', 'color_mlp.pt'\] nor checkpoints.pth is there"):
        Decoders(tmp_path)
    blob = {"opacity_mlp": _sd((4, 3), (1, 4)), "cov_mlp": _sd((4, 3), (7, 4)), "color_mlp": _sd((4, 3), (3, 4)),
            "appearance": {"embedding.weight": torch.ones(2, 5)}}
    torch.save(blob, tmp_path / "checkpoints.pth")
    dec = Decoders(tmp_path)
    assert dec.mode == "unite" and sorted(dec.state) == ["embedding_appearance", "mlp_color", "mlp_cov", "mlp_opacity"]
    assert dec.source["mlp_cov"] == f"{tmp_path / 'checkpoints.pth'} ['cov_mlp']"
    mods = dec.modules()
    assert mods["embedding_appearance"].weight.shape == (2, 5) and mods["mlp_color"][2].out_features == 3
    assert torch.equal(dec.weight("mlp_cov", "2.bias"), blob["cov_mlp"]["2.bias"])
    with pytest.raises(FileFormatError, match=r"\['cov_mlp'\]: decoder 'mlp_cov' has no tensor '4.weight' \(keys: "):
        dec.weight("mlp_cov", "4.weight")
    torch.save({**blob, "cov_mlp": [1]}, tmp_path / "checkpoints.pth")
    with pytest.raises(FileFormatError, match=r"checkpoints.pth: entry 'cov_mlp' is not a state dict$"):
        Decoders(tmp_path)
    torch.save({k: v for k, v in blob.items() if k not in ("color_mlp", "opacity_mlp")}, tmp_path / "checkpoints.pth")
    with pytest.raises(FileFormatError, match=r"checkpoints.pth: missing MLP entr\(y/ies\) \['opacity_mlp', 'color_mlp'\]"):
        Decoders(tmp_path)
    torch.save([blob], tmp_path / "checkpoints.pth")
    with pytest.raises(FileFormatError, match="checkpoints.pth: expected a dict of state dicts, got list"):
        Decoders(tmp_path)


def test_decoders_split_mode_from_traces(tmp_path):
    from torch import nn

    from controlgs_adapter.formats.decoders import Decoders

    torch.manual_seed(0)
    nets = {"opacity_mlp.pt": nn.Sequential(nn.Linear(3, 4), nn.ReLU(), nn.Linear(4, 1), nn.Tanh()),
            "cov_mlp.pt": nn.Sequential(nn.Linear(3, 4), nn.ReLU(), nn.Linear(4, 7))}
    for name, net in nets.items():
        torch.jit.trace(net, torch.zeros(2, 3)).save(str(tmp_path / name))
    with pytest.raises(FileFormatError, match=r"missing MLP file\(s\) \['color_mlp.pt'\] \(split mode"):
        Decoders(tmp_path)
    torch.save({"opacity_mlp": {}}, tmp_path / "checkpoints.pth")  # ignored: any trace present means split mode
    nets["color_mlp.pt"] = nn.Sequential(nn.Linear(3, 4), nn.ReLU(), nn.Linear(4, 3), nn.Sigmoid())
    torch.jit.trace(nets["color_mlp.pt"], torch.zeros(2, 3)).save(str(tmp_path / "color_mlp.pt"))
    dec = Decoders(tmp_path)
    assert dec.mode == "split" and dec.source["mlp_cov"] == str(tmp_path / "cov_mlp.pt")
    assert dec.layers["mlp_opacity"] == [("Linear", (3, 4)), ("ReLU", None), ("Linear", (4, 1)), ("Tanh", None)]
    x = torch.randn(5, 3)
    mods = dec.modules()
    for attr, file in [("mlp_opacity", "opacity_mlp.pt"), ("mlp_cov", "cov_mlp.pt"), ("mlp_color", "color_mlp.pt")]:
        assert torch.equal(mods[attr](x), nets[file](x))


# --- added after batch T2's first run (m231, m235, m241, m242)


def test_yaml_hash_inside_a_value_is_not_a_comment(tmp_path):
    (tmp_path / "c.yaml").write_text("tag: v1#2\ncolour: '#ff0000'\nsize: 3 # a comment\n#whole: 1\n")
    assert bb.read_yaml_scalars(tmp_path / "c.yaml") == {"tag": ["v1#2"], "colour": ["#ff0000"], "size": [3]}


def test_row_map_bounds_the_source_index_by_the_saved_rows(tmp_path):
    from test_backend_contextgs import PAD, A, _arrays, _decoders, _model, _write_dir

    from controlgs_adapter.backends.contextgs import ContextGSBackend, load_contextgs_dir
    from controlgs_adapter.formats.adapter import row_map, valid_fingerprint

    arr, decs = _arrays(7, decoded=True), _decoders(7)
    arr["mask"][3] = 0.0
    live, loaded = _model(arr, decs, decoded=True), load_contextgs_dir(_write_dir(tmp_path / "s", arr, decs))
    backend = ContextGSBackend()
    spec = {"valid_fingerprint": valid_fingerprint(live, backend), "num_anchors": A}
    kind, rows = row_map(loaded, backend, spec)
    assert kind == "gather" and rows.tolist() == [i for i in range(A - PAD) if i != 3]
    source = loaded.source_index.clone()
    loaded.source_index = source.clone()
    loaded.source_index[-1] = A - 1  # the last saved row: still a row of the file
    assert row_map(loaded, backend, spec)[0] == "gather"
    loaded.source_index[-1] = A  # one past the saved rows: no mapping
    assert row_map(loaded, backend, spec) is None
    assert row_map(loaded, backend, {**spec, "valid_fingerprint": 1}) is None
    loaded.source_index = source
    assert row_map(loaded, backend, {**spec, "num_anchors": A - PAD - 1}) is None  # same count: nothing to map


@pytest.mark.parametrize("beta, threshold", [(0.5, 20.0), (1.0, 1.5), (2.0, 10.0)])
def test_softplus_settings_come_from_the_archive(tmp_path, beta, threshold):
    from torch import nn

    from controlgs_adapter.formats.torchscript import eager_from_archive

    eager = nn.Sequential(nn.Linear(1, 1), nn.Softplus(beta=beta, threshold=threshold)).eval()
    with torch.no_grad():
        eager[0].weight.fill_(1.0)
        eager[0].bias.zero_()
    for mode in ("trace", "script"):
        path = tmp_path / f"sp_{mode}.pt"
        with warnings.catch_warnings():  # torch's deprecation of TorchScript: the families' format all the same
            warnings.simplefilter("ignore", DeprecationWarning)
            sm = torch.jit.trace(eager, torch.zeros(2, 1)) if mode == "trace" else torch.jit.script(eager)
            sm.save(str(path))
        rebuilt = eager_from_archive(path)
        x = torch.tensor([[-3.0], [0.0], [0.5], [1.0], [2.0], [4.0], [8.0], [12.0]], dtype=torch.float64)
        want = torch.where(beta * x > threshold, x, torch.log1p(torch.exp(beta * x)) / beta)  # float64 by hand
        torch.testing.assert_close(rebuilt.double()(x), want, rtol=1e-12, atol=1e-12)


def test_tensor_record_one_element_past_its_storage_is_refused(tmp_path):
    import zipfile

    from torch import nn

    from controlgs_adapter.formats.torchscript import eager_from_archive

    src = tmp_path / "l.pt"
    net = nn.Sequential(nn.Linear(2, 3))
    torch.jit.trace(net, torch.zeros(1, 2)).save(str(src))
    with zipfile.ZipFile(src) as z:
        pkl_name = next(n for n in z.namelist() if n.endswith("/data.pkl"))
        pkl = z.read(pkl_name)
    record = b"K\x00(K\x03K\x02t(K\x02K\x01t"  # weight: offset 0, size (3, 2), stride (2, 1) in a 6-element storage
    assert pkl.count(record) == 1

    def patched(new: bytes):
        dst = tmp_path / f"p{len(list(tmp_path.iterdir()))}.pt"
        with zipfile.ZipFile(src) as zin, zipfile.ZipFile(dst, "w") as zout:
            for info in zin.infolist():
                zout.writestr(info, pkl.replace(record, new) if info.filename == pkl_name else zin.read(info))
        return dst

    # offset 1: the last element is index 1 + 2*2 + 1 = 6, one past the storage's 0..5
    with pytest.raises(FileFormatError, match=r"p\d+.pt: .*a tensor of shape \[3, 2\] that reaches past its storage data/0"):
        eager_from_archive(patched(b"K\x01(K\x03K\x02t(K\x02K\x01t"))
    # stride (1, 3): element [i, j] is storage index i + 3 j, the last one 2 + 3 = 5: in bounds
    ok = eager_from_archive(patched(b"K\x00(K\x03K\x02t(K\x01K\x03t"))
    flat = net[0].weight.detach().flatten()
    assert ok[0].weight.tolist() == [[flat[i + 3 * j].item() for j in range(2)] for i in range(3)]


def _linear_archive(tmp_path):
    """A traced ``Sequential(Linear(2, 3))`` archive, its eager module, and a function writing a copy
    with entries replaced (``name suffix -> bytes``, None drops the entry)."""
    import zipfile

    from torch import nn

    src = tmp_path / "lin.pt"
    net = nn.Sequential(nn.Linear(2, 3))
    torch.jit.trace(net, torch.zeros(1, 2)).save(str(src))

    def patched(edit: dict[str, bytes | None], name: str) -> object:
        dst = tmp_path / name
        with zipfile.ZipFile(src) as zin, zipfile.ZipFile(dst, "w") as zout:
            for info in zin.infolist():
                hit = next((k for k in edit if info.filename.endswith(k)), None)
                if hit is None:
                    zout.writestr(info, zin.read(info))
                elif edit[hit] is not None:
                    zout.writestr(info.filename, edit[hit])  # type: ignore[arg-type]
        return dst

    with zipfile.ZipFile(src) as z:
        pkl = z.read(next(n for n in z.namelist() if n.endswith("/data.pkl")))
    return src, net, patched, pkl


def test_archive_container_refusals_name_file_and_cause(tmp_path):
    from controlgs_adapter.formats.torchscript import eager_from_archive, tensors_from_archive

    src, net, patched, pkl = _linear_archive(tmp_path)
    assert torch.equal(eager_from_archive(src)[0].weight, net[0].weight)
    cases = [
        ({"/byteorder": b"big"}, "a.pt", "refused (nothing in it was run): big-endian tensor data"),
        ({"/data/0": None}, "b.pt", "refused (nothing in it was run): no entry 'lin/data/0'"),
        ({"/data/0": bytes(20)}, "c.pt", "storage data/0 holds 20 bytes, its record needs 24"),
        ({"/data.pkl": pkl.replace(b"K\x00(K\x03K\x02t", b"J\xff\xff\xff\xff(K\x03K\x02t")}, "d.pt", "a malformed tensor record"),
        ({"/data.pkl": pkl.replace(b"(K\x03K\x02t(K\x02K\x01t", b"(K\x03K\x02t(K\x02t")}, "e.pt", "a malformed tensor record"),
        ({"/data.pkl": None}, "f.pt", "no <name>/data.pkl (not a TorchScript or torch.save zip archive)"),
    ]
    for edit, name, words in cases:
        with pytest.raises(FileFormatError, match=rf"{name}: ") as e:
            eager_from_archive(patched(edit, name))
        assert words in str(e.value), (name, str(e.value))
    torch.save(net.state_dict(), tmp_path / "sd.pt")
    with pytest.raises(FileFormatError, match=r"sd.pt: .*no code/ folder \(not a TorchScript archive; a torch.save file\?\)"):
        eager_from_archive(tmp_path / "sd.pt")
    with pytest.raises(FileFormatError, match="a.pt: .*big-endian tensor data"):
        tensors_from_archive(tmp_path / "a.pt")
    assert eager_from_archive(patched({"/byteorder": b"little\n"}, "g.pt"))[0].bias.tolist() == net[0].bias.tolist()


def test_archive_size_bound_is_on_the_total_of_its_entries(tmp_path, monkeypatch):
    import zipfile

    from controlgs_adapter.formats import torchscript as ts

    src, net, _, _ = _linear_archive(tmp_path)
    with zipfile.ZipFile(src) as z:
        sizes = [i.file_size for i in z.infolist()]
    assert max(sizes) < sum(sizes) - 1
    monkeypatch.setattr(ts, "_MAX_TOTAL_BYTES", sum(sizes))
    assert torch.equal(ts.eager_from_archive(src)[0].weight, net[0].weight)  # exactly at the bound
    monkeypatch.setattr(ts, "_MAX_TOTAL_BYTES", sum(sizes) - 1)  # every entry fits, their total does not
    with pytest.raises(FileFormatError, match=rf"lin.pt: .*an uncompressed size over {sum(sizes) - 1} bytes"):
        ts.eager_from_archive(src)


@pytest.mark.parametrize("drop", ["lr", "loss"])
def test_checkpoint_missing_a_config_field_is_another_run(tmp_path, drop):
    from controlgs_adapter.formats.checkpoint import read_checkpoint

    c = _ckpt()
    header = c.header()
    header["config"] = {k: v for k, v in c.config.items() if k != drop}
    _raw_ckpt(tmp_path / "c.safetensors", c.tensors(), header)
    with pytest.raises(FileFormatError, match=rf"c.safetensors: checkpoint was written with a different config \({drop}\)"):
        read_checkpoint(tmp_path / "c.safetensors", c, _SHAPES)
