"""Backbone files read as data, bounds pinned at their documented values: the cfg_args term budget
at exactly 100 000 parse-tree nodes, the ASCII PLY size pre-check on the smallest valid body, the
Scaffold offset layout worked out by hand, and the umask modes of written files and folders."""

from __future__ import annotations

import ast
import os

import numpy as np
import pytest

from controlgs_adapter.errors import FileFormatError
from controlgs_adapter.formats import backbone as bb
from controlgs_adapter.formats import safetensors as st


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


@pytest.mark.parametrize("mask, file_bits, folder_bits", [(0o022, 0o644, 0o755), (0o077, 0o600, 0o700), (0o027, 0o640, 0o750)])
def test_modes_follow_the_umask(tmp_path, mask, file_bits, folder_bits):
    old = os.umask(mask)
    try:
        assert st.file_mode() == file_bits and st.folder_mode() == folder_bits
        out = st.atomic_write(tmp_path / "f.bin", lambda tmp: open(tmp, "wb").write(b"x"))
        assert out.stat().st_mode & 0o777 == file_bits
    finally:
        os.umask(old)


def test_pid_alive():
    import subprocess
    import sys

    assert st._pid_alive(os.getpid())
    dead = int(subprocess.run([sys.executable, "-c", "import os; print(os.getpid())"], capture_output=True, text=True,
                              check=True).stdout)
    assert not st._pid_alive(dead)


def test_state_dict_file_must_be_a_dict(tmp_path):
    import torch

    torch.save([torch.zeros(2)], tmp_path / "l.pth")
    with pytest.raises(FileFormatError, match=r"l\.pth: expected a dict of state dicts, got list"):
        bb.load_state_dict_file(tmp_path / "l.pth")
    with pytest.raises(FileFormatError, match=r"none\.pth: no such file"):
        bb.load_state_dict_file(tmp_path / "none.pth")
    torch.save({"a": {"w": torch.ones(2)}}, tmp_path / "d.pth")
    assert torch.equal(bb.load_state_dict_file(tmp_path / "d.pth")["a"]["w"], torch.ones(2))


def test_load_tensors_unreadable_data_names_the_file(tmp_path):
    import torch

    p = st.save_tensors(tmp_path / "x.safetensors", {"a": torch.ones(2)}, {}, kind="k", format_version=1)
    with pytest.raises(FileFormatError, match=r"x\.safetensors: tensor data unreadable"):
        st.load_tensors(p, kind="k", max_version=1, device="nope")
    tensors, header = st.load_tensors(p, kind="k", max_version=1, device="cpu")
    assert torch.equal(tensors["a"], torch.ones(2)) and header["kind"] == "k"


@pytest.mark.filterwarnings("ignore::DeprecationWarning")
def test_trusted_torchscript_paths_name_the_file(tmp_path):
    """``trust_code=True`` on archives this test wrote itself (the opt-in path: ``torch.jit.load``)."""
    import warnings

    import torch
    from torch import nn

    from controlgs_adapter.formats.torchscript import tensors_from_archive

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


def test_checkpoint_at_iteration_zero_with_integer_losses(tmp_path):
    """The smallest well-formed header values: iteration 0 (>= 0 is documented) and integer losses."""
    import torch

    from controlgs_adapter.formats.checkpoint import Checkpoint, read_checkpoint, write_checkpoint

    c = Checkpoint(adapter={"conditions": torch.zeros(2, 1, 2)}, optimizer_state={},
                   param_groups=[{"lr": 0.1, "params": [0]}], rng=torch.zeros(4, dtype=torch.uint8), iteration=0,
                   history=[2, 1], config={"lr": 0.1, "iterations": 5, "loss": {}}, modules=["lens"], effects=[],
                   fingerprint="f", data="d")
    p = write_checkpoint(tmp_path / "c.safetensors", c)
    back = read_checkpoint(p, c, [torch.Size([2, 1, 2])])
    assert back.iteration == 0 and back.history == [2, 1] and back.optimizer_state == {}
    assert back.param_groups == [{"lr": 0.1, "params": [0]}] and back.effects == []
