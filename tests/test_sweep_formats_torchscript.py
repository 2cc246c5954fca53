"""TorchScript archives read as data: the documented bounds at their exact values (entries, nesting,
tensor dims), every storage type the reader knows mapped to its dtype, and the rebuild of a live
script module (settings read from its code, train mode, requires_grad) compared with eager modules
built by hand. Nothing here loads an archive the trusted way except to build reference outputs."""

from __future__ import annotations

import warnings
import zipfile
from pathlib import Path

import pytest
import torch
from torch import nn

from controlgs_adapter.errors import FileFormatError, TargetError
from controlgs_adapter.formats.torchscript import eager_from_archive, eager_from_script, tensors_from_archive

pytestmark = pytest.mark.filterwarnings("ignore::DeprecationWarning")


def _trace(module: nn.Module, path: Path, in_features: int, dtype: torch.dtype = torch.float32) -> Path:
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        torch.jit.save(torch.jit.trace(module, torch.randn(2, in_features, dtype=dtype)), str(path))
    return path


def _script(module: nn.Module, path: Path) -> Path:
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        torch.jit.save(torch.jit.script(module), str(path))
    return path


def _with_extra_entries(src: Path, dst: Path, total: int) -> Path:
    """A copy of ``src`` padded with empty entries to exactly ``total`` zip entries."""
    with zipfile.ZipFile(src) as zin, zipfile.ZipFile(dst, "w") as zout:
        infos = zin.infolist()
        prefix = infos[0].filename.split("/")[0]
        for info in infos:
            zout.writestr(info, zin.read(info))
        for i in range(total - len(infos)):
            zout.writestr(f"{prefix}/extra/{i}", b"")
    with zipfile.ZipFile(dst) as z:
        assert len(z.infolist()) == total
    return dst


def test_entry_count_bound_is_4096(tmp_path):
    src = _trace(nn.Sequential(nn.Linear(3, 2)), tmp_path / "a.pt", 3)
    ok = eager_from_archive(_with_extra_entries(src, tmp_path / "ok.pt", 4096))  # at the bound: read
    assert isinstance(ok, nn.Sequential)
    with pytest.raises(FileFormatError, match=r"over\.pt: TorchScript archive refused .*4097 zip entries \(at most 4096"):
        eager_from_archive(_with_extra_entries(src, tmp_path / "over.pt", 4097))


def _nested(k: int) -> nn.Module:
    m: nn.Module = nn.Linear(2, 2)
    for _ in range(k):
        m = nn.Sequential(m)
    return m


def test_nesting_bound_is_32_levels(tmp_path):
    torch.manual_seed(0)
    m = _nested(32)  # the Linear sits at depth 32 (the root is depth 0)
    got = eager_from_archive(_trace(m, tmp_path / "n32.pt", 2))
    x = torch.randn(5, 2)
    assert torch.equal(got(x), m(x))
    with pytest.raises(FileFormatError, match=r"n33\.pt: .*modules nested deeper than 32 \(or a cycle\) at 0(\.0){32}$"):
        eager_from_archive(_trace(_nested(33), tmp_path / "n33.pt", 2))


class _Buffers(nn.Module):
    def __init__(self, **tensors: torch.Tensor) -> None:
        super().__init__()
        for k, v in tensors.items():
            self.register_buffer(k, v)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return x


def test_tensor_dims_bound_is_8(tmp_path):
    t8 = torch.arange(2.0).reshape([1] * 7 + [2])
    got = tensors_from_archive(_script(_Buffers(t=t8), tmp_path / "d8.pt"))
    assert got["t"].shape == t8.shape and torch.equal(got["t"], t8)
    with pytest.raises(FileFormatError, match=r"d9\.pt: TorchScript archive refused .*a malformed tensor record"):
        tensors_from_archive(_script(_Buffers(t=torch.zeros([1] * 9)), tmp_path / "d9.pt"))


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64, torch.float16, torch.bfloat16])
def test_float_storages_keep_their_dtype_and_values(tmp_path, dtype):
    g = torch.Generator().manual_seed(1)
    w = torch.randn(3, 4, generator=g).to(dtype)
    emb = torch.randn(2, 3, generator=g).to(dtype)
    got = tensors_from_archive(_script(_Buffers(w=w, emb=emb), tmp_path / "t.pt"))
    assert set(got) == {"w", "emb"}
    for k, v in (("w", w), ("emb", emb)):
        assert got[k].dtype == dtype and torch.equal(got[k], v), k


@pytest.mark.parametrize("dtype", [torch.float64, torch.float16])
def test_linear_archives_in_other_float_dtypes(tmp_path, dtype):
    torch.manual_seed(2)
    m = nn.Sequential(nn.Linear(4, 3), nn.Tanh()).to(dtype)
    rebuilt = eager_from_archive(_trace(m, tmp_path / "m.pt", 4, dtype))
    assert rebuilt[0].weight.dtype == dtype and torch.equal(rebuilt[0].weight, m[0].weight)
    assert torch.equal(rebuilt[0].bias, m[0].bias)


@pytest.mark.parametrize("dtype", [torch.int64, torch.int32, torch.int16, torch.int8, torch.uint8, torch.bool,
                                   torch.complex64, torch.complex128])
def test_non_float_storages_are_refused_naming_the_dtype(tmp_path, dtype):
    t = torch.ones(3).to(dtype)
    with pytest.raises(FileFormatError, match=rf"t\.pt: TorchScript archive refused .*a non-float tensor \({dtype}\); "
                                              r"decoders hold floating-point weights only"):
        tensors_from_archive(_script(_Buffers(t=t), tmp_path / "t.pt"))


def test_nested_tensor_names_and_nan_refusal(tmp_path):
    torch.manual_seed(3)
    m = nn.Sequential(nn.Linear(2, 3), nn.Sequential(nn.Linear(3, 1, bias=False)))
    got = tensors_from_archive(_trace(m, tmp_path / "m.pt", 2))
    assert list(got) == ["0.weight", "0.bias", "1.0.weight"]
    for k, v in m.state_dict().items():
        assert torch.equal(got[k], v)
    with torch.no_grad():
        m[1][0].weight[0, 1] = float("inf")
    with pytest.raises(FileFormatError, match=r"non-finite weights \(inf\) in 1\.0\.weight"):
        tensors_from_archive(_trace(m, tmp_path / "inf.pt", 2))


# ------------------------------------------------------------------------------------ live script modules

def _jit(module: nn.Module, how: str, in_features: int) -> torch.jit.ScriptModule:
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return torch.jit.trace(module, torch.randn(2, in_features)) if how == "trace" else torch.jit.script(module)


@pytest.mark.parametrize("how", ["trace", "script"])
def test_script_rebuild_reads_each_setting(how):
    torch.manual_seed(4)
    # settings away from torch's defaults (LeakyReLU 0.01, Softplus beta 1 / threshold 20, Softmax dim None)
    m = nn.Sequential(nn.Linear(3, 6), nn.LeakyReLU(0.3), nn.Linear(6, 6), nn.Softplus(beta=3.0, threshold=0.5),
                      nn.Linear(6, 4), nn.Softmax(dim=0)).eval()
    got = eager_from_script(_jit(m, how, 3), name="dec")
    assert got[1].negative_slope == 0.3
    assert (got[3].beta, got[3].threshold) == (3.0, 0.5)
    assert got[5].dim == 0
    x = torch.randn(7, 3) * 4
    assert torch.equal(got(x), m(x))


def test_script_rebuild_keeps_mode_grad_flags_and_refuses():
    torch.manual_seed(5)
    m = nn.Sequential(nn.Linear(3, 2), nn.ReLU()).train()
    m[0].bias.requires_grad_(False)
    got = eager_from_script(_jit(m, "script", 3))
    assert got.training and got[0].weight.requires_grad and not got[0].bias.requires_grad
    m.eval()
    assert not eager_from_script(_jit(m, "script", 3)).training
    nobias = nn.Sequential(nn.Linear(3, 2, bias=False))
    got = eager_from_script(_jit(nobias, "trace", 3))
    assert got[0].bias is None and torch.equal(got[0].weight, nobias[0].weight)
    with pytest.raises(TargetError, match="decoder 'act': the TorchScript module holds no Linear layer"):
        eager_from_script(_jit(nn.Sequential(nn.ReLU()), "script", 3), name="act")
    with pytest.raises(TargetError, match="decoder 'x': expected a TorchScript module, got Sequential"):
        eager_from_script(m, name="x")  # type: ignore[arg-type]
    with pytest.raises(TargetError, match=r"decoder 'g.1': TorchScript layer of type 'GELU' cannot be rebuilt"):
        eager_from_script(_jit(nn.Sequential(nn.Linear(3, 2), nn.GELU()), "script", 3), name="g")


def _padded(src: Path, dst: Path, suffix: str, pad: bytes) -> Path:
    """A copy of ``src`` whose entry ending in ``suffix`` gets ``pad`` appended (compressed: small on disk)."""
    with zipfile.ZipFile(src) as zin, zipfile.ZipFile(dst, "w", zipfile.ZIP_DEFLATED) as zout:
        for info in zin.infolist():
            data = zin.read(info)
            zout.writestr(info.filename, data + pad if info.filename.endswith(suffix) else data)
    return dst


def test_pickle_bound_is_16_mib(tmp_path):
    src = _trace(nn.Sequential(nn.Linear(3, 2)), tmp_path / "a.pt", 3)
    with zipfile.ZipFile(src) as z:
        size = len(z.read("a/data.pkl"))
    # bytes after the pickle's STOP opcode are never read by the unpickler: only the entry's size matters
    ok = _padded(src, tmp_path / "ok.pt", "/data.pkl", b"\0" * ((16 << 20) - size))
    assert isinstance(eager_from_archive(ok), nn.Sequential)
    over = _padded(src, tmp_path / "over.pt", "/data.pkl", b"\0" * ((16 << 20) + 1 - size))
    with pytest.raises(FileFormatError, match=r"over\.pt: .*entry 'a/data\.pkl' of 16777217 bytes \(at most 16777216\)"):
        eager_from_archive(over)


def test_code_bound_is_4_mib_in_all(tmp_path):
    src = _trace(nn.Sequential(nn.Linear(3, 2)), tmp_path / "a.pt", 3)
    with zipfile.ZipFile(src) as z:
        code = {n: len(z.read(n)) for n in z.namelist() if n.startswith("a/code/") and n.endswith(".py")}
    assert len(code) == 2  # container and linear (their paths may carry a ___torch_mangle_<n> part)
    target = next(n for n in code if "/linear" in n)
    pad = (4 << 20) - sum(code.values())  # a trailing comment: still valid source
    ok = _padded(src, tmp_path / "ok.pt", target, b"\n#" + b"x" * (pad - 3) + b"\n")
    assert isinstance(eager_from_archive(ok), nn.Sequential)
    over = _padded(src, tmp_path / "over.pt", target, b"\n#" + b"x" * (pad - 2) + b"\n")
    with pytest.raises(FileFormatError, match=r"over\.pt: .*over 4194304 bytes of code"):
        eager_from_archive(over)


def _declaring(src: Path, dst: Path, declared: int) -> Path:
    """A copy of ``src`` with one more (empty, never read) entry whose central-directory record
    declares ``declared`` uncompressed bytes (offset 24 of the record, little-endian uint32)."""
    import struct

    with zipfile.ZipFile(src) as zin, zipfile.ZipFile(dst, "w") as zout:
        for info in zin.infolist():
            zout.writestr(info, zin.read(info))
        zout.writestr("a/extra/declared", b"")
    raw = bytearray(dst.read_bytes())
    at = raw.rindex(b"PK\x01\x02")  # the last central-directory record: the entry just added
    assert raw[at + 46: at + 46 + len("a/extra/declared")] == b"a/extra/declared"
    raw[at + 24: at + 28] = struct.pack("<I", declared)
    dst.write_bytes(bytes(raw))
    return dst


def test_total_size_bound_is_1_gib_declared(tmp_path):
    src = _trace(nn.Sequential(nn.Linear(3, 2)), tmp_path / "a.pt", 3)
    with zipfile.ZipFile(src) as z:
        used = sum(i.file_size for i in z.infolist())
    ok = _declaring(src, tmp_path / "ok.pt", (1 << 30) - used)
    with zipfile.ZipFile(ok) as z:
        assert sum(i.file_size for i in z.infolist()) == 1 << 30
    assert isinstance(eager_from_archive(ok), nn.Sequential)
    with pytest.raises(FileFormatError, match=r"over\.pt: .*an uncompressed size over 1073741824 bytes"):
        eager_from_archive(_declaring(src, tmp_path / "over.pt", (1 << 30) + 1 - used))


@pytest.mark.parametrize("after, what", [(b"ctorch\nFloatStorage\n", "a pickled BUILD on a storage type"),
                                         (b"Q", "a pickled BUILD on a storage record")])
def test_pickled_build_on_storage_objects_is_refused(tmp_path, after, what):
    """pickle's BUILD updates an object's ``__dict__`` directly (a frozen dataclass does not stop it): a
    storage type renamed that way ('LongStorage' called 'FloatStorage') would pass the float-only check."""
    src = _trace(nn.Sequential(nn.Linear(3, 2)), tmp_path / "a.pt", 3)
    with zipfile.ZipFile(src) as z:
        pkl = z.read("a/data.pkl")
    assert after in pkl
    at = pkl.index(after) + len(after)
    bad = pkl[:at] + b"}b" + pkl[at:]  # EMPTY_DICT, BUILD on the object just pushed
    dst = tmp_path / "build.pt"
    with zipfile.ZipFile(src) as zin, zipfile.ZipFile(dst, "w") as zout:
        for info in zin.infolist():
            zout.writestr(info, bad if info.filename == "a/data.pkl" else zin.read(info))
    with pytest.raises(FileFormatError, match=rf"build\.pt: TorchScript archive refused \(nothing in it was run\): {what}"):
        eager_from_archive(dst)
    with pytest.raises(FileFormatError, match=what):
        tensors_from_archive(dst)


@pytest.mark.parametrize("glob, named", [(b"ctorch\nload\n", "'torch.load'"), (b"cos\nFloatStorage\n", "'os.FloatStorage'"),
                                         (b"cos\nLongStorage\n", "'os.LongStorage'"),
                                         (b"ctorch.nn\nLongStorage\n", "'torch.nn.LongStorage'"),
                                         (b"ctorch\nTensor\n", "'torch.Tensor'")])
def test_storage_globals_only_from_the_torch_module(tmp_path, glob, named):
    """Only ``torch.<Name>Storage`` is a storage type; the same names from another module, and other
    ``torch`` globals, are refused by name (never looked up in the storage tables)."""
    src = _trace(nn.Sequential(nn.Linear(3, 2)), tmp_path / "a.pt", 3)
    with zipfile.ZipFile(src) as z:
        pkl = z.read("a/data.pkl")
    dst = tmp_path / "g.pt"
    with zipfile.ZipFile(src) as zin, zipfile.ZipFile(dst, "w") as zout:
        for info in zin.infolist():
            data = zin.read(info)
            zout.writestr(info, pkl.replace(b"ctorch\nFloatStorage\n", glob, 1) if info.filename == "a/data.pkl" else data)
    with pytest.raises(FileFormatError, match=rf"g\.pt: TorchScript archive refused \(nothing in it was run\): a pickled "
                                              rf"reference to the global {named}, which a decoder never holds"):
        eager_from_archive(dst)
