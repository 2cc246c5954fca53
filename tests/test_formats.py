from pathlib import Path

import numpy as np
import pytest
import torch
from hypothesis import given, settings, strategies as st

from controlgs_adapter.formats.backbone import (load_state_dict_file, parse_cfg_args, read_ply, write_ply,
                                                 load_torchscript)
from controlgs_adapter.errors import FileFormatError


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
