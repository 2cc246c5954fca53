"""Decoder archives read as data (``formats.torchscript``): every supported layer rebuilt as an eager module
with the archive's weights and settings, and anything else refused before any of it runs: code that is not
a plain chain of supported layers, pickles naming other globals, malformed tensor records, and archives
past the bounds on entries, nesting, pickle, code and total size."""

from __future__ import annotations

import os
import pickle
import re
import struct
import subprocess
import sys
import warnings
import zipfile
from pathlib import Path

import pytest
import torch
from helpers.decoder_kinds import DECODERS, F
from helpers.hostile_modules import Loop, SetState, Writer
from torch import nn

import controlgs_adapter.formats.torchscript as ts
from controlgs_adapter.errors import FileFormatError
from controlgs_adapter.formats.backbone import load_torchscript
from controlgs_adapter.formats.torchscript import eager_from_archive, tensors_from_archive

pytestmark = pytest.mark.filterwarnings("ignore::DeprecationWarning")


def _save(module: nn.Module, path: Path, mode: str = "trace", in_features: int | None = None,
          dtype: torch.dtype = torch.float32) -> Path:
    """``module`` traced (on a ``[3, in_features]`` input) or scripted, saved at ``path``."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        sm = torch.jit.trace(module, torch.randn(3, in_features, dtype=dtype)) if mode == "trace" else torch.jit.script(module)
        torch.jit.save(sm, str(path))
    return path


def _reference(path: Path) -> torch.jit.ScriptModule:
    """An archive this test made itself, loaded the trusted way, for reference outputs."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return torch.jit.load(str(path))


def _refused(path: Path, *what: str) -> str:
    """``eager_from_archive(path)`` refuses, naming the file and each of ``what``; returns the message."""
    with pytest.raises(FileFormatError) as info:
        eager_from_archive(path)
    msg = str(info.value)
    assert str(path) in msg, msg
    for w in what:
        assert w in msg, msg
    return msg


def _patched(src: Path, dst: Path, edit: dict[str, bytes | None], extra: dict[str, bytes] | None = None) -> Path:
    """A copy of the zip ``src`` with entries ending in a key of ``edit`` replaced (or dropped for None) and
    ``extra`` entries (names relative to the archive's folder) added."""
    with zipfile.ZipFile(src) as zin, zipfile.ZipFile(dst, "w") as zout:
        prefix = zin.namelist()[0].split("/")[0]
        for info in zin.infolist():
            hit = next((k for k in edit if info.filename.endswith(k)), None)
            if hit is None:
                zout.writestr(info, zin.read(info))
            elif edit[hit] is not None:
                zout.writestr(info.filename, edit[hit])
        for name, data in (extra or {}).items():
            zout.writestr(f"{prefix}/{name}", data)
    return dst


def _with_entries(src: Path, dst: Path, entries: dict[str, bytes]) -> Path:
    """A copy of ``src`` with ``entries`` (name relative to the archive's folder) replaced or added."""
    with zipfile.ZipFile(src) as zin, zipfile.ZipFile(dst, "w") as zout:
        prefix = zin.namelist()[0].split("/")[0]
        full = {f"{prefix}/{k}": v for k, v in entries.items()}
        for info in zin.infolist():
            zout.writestr(info, full.pop(info.filename, None) or zin.read(info))
        for name, data in full.items():
            zout.writestr(name, data)
    return dst


def _edited(src: Path, dst: Path, old: str, new: str) -> Path:
    """A copy of ``src`` whose one code file containing ``old`` has it replaced by ``new`` (once)."""
    hits = 0
    with zipfile.ZipFile(src) as zin, zipfile.ZipFile(dst, "w") as zout:
        for info in zin.infolist():
            data = zin.read(info)
            if info.filename.endswith(".py") and old.encode() in data:
                hits += data.count(old.encode())
                data = data.replace(old.encode(), new.encode())
            zout.writestr(info, data)
    assert hits == 1, f"{old!r} found {hits} times"
    return dst


def _padded(src: Path, dst: Path, suffix: str, pad: bytes) -> Path:
    """A copy of ``src`` whose entry ending in ``suffix`` gets ``pad`` appended (compressed: small on disk)."""
    with zipfile.ZipFile(src) as zin, zipfile.ZipFile(dst, "w", zipfile.ZIP_DEFLATED) as zout:
        for info in zin.infolist():
            data = zin.read(info)
            zout.writestr(info.filename, data + pad if info.filename.endswith(suffix) else data)
    return dst


def _declaring(src: Path, dst: Path, declared: int) -> Path:
    """A copy of ``src`` with one more (empty, never read) entry whose central-directory record
    declares ``declared`` uncompressed bytes (offset 24 of the record, little-endian uint32)."""

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


class _Buffers(nn.Module):
    def __init__(self, **tensors: torch.Tensor) -> None:
        super().__init__()
        for k, v in tensors.items():
            self.register_buffer(k, v)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return x


def _plain(tmp_path: Path) -> Path:
    """A traced Scaffold-GS opacity decoder."""
    return _save(DECODERS["opacity"](), tmp_path / "plain.pt", "trace", F + 3)


def _code_of(src: Path, cls: str) -> tuple[str, str]:
    """(entry name, text) of the code file of ``src`` that defines ``class <cls>`` (names may be mangled)."""
    with zipfile.ZipFile(src) as z:
        for name in z.namelist():
            if name.endswith(".py") and f"class {cls}(" in z.read(name).decode():
                return name, z.read(name).decode()
    raise AssertionError(f"no class {cls} in {src}")


def _with(module: nn.Module, **state: object) -> nn.Module:
    """``module`` with extra attributes set (a plain value, or a tensor as a buffer)."""
    for k, v in state.items():
        if isinstance(v, torch.Tensor):
            module.register_buffer(k, v)
        else:
            setattr(module, k, v)
    return module


def _linear(bias: torch.Tensor | None = None, weight: torch.Tensor | None = None) -> nn.Linear:
    lin = nn.Linear(3, 2)
    if bias is not None:
        lin.bias = nn.Parameter(bias)
    if weight is not None:
        lin.weight = nn.Parameter(weight)
    return lin


def _traced_two_levels(tmp_path: Path, name: str, fill: float | None = None) -> tuple[Path, nn.Module]:
    """A traced nested Sequential; ``fill`` written into the inner Linear's bias[1]; the outer weight frozen."""
    module = nn.Sequential(nn.Linear(3, 4), nn.Sequential(nn.Linear(4, 2), nn.Tanh()))
    module[0].weight.requires_grad_(False)
    if fill is not None:
        with torch.no_grad():
            module[1][0].bias[1] = fill
    path = tmp_path / name
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        torch.jit.save(torch.jit.trace(module, torch.randn(2, 3), check_trace=False), str(path))
    return path, module


def _ints(values: tuple[int, ...]) -> bytes:
    return b"(" + b"".join(b"J" + v.to_bytes(4, "little", signed=True) for v in values) + b"t"


def _record(size: tuple[int, ...], stride: tuple[int, ...], offset: int = 0, requires_grad: bytes = b"\x89",
            hooks: bytes = b"", storage: bytes = b"FloatStorage", numel: int = 6) -> bytes:
    """Opcodes of ``torch._utils._rebuild_tensor_v2(storage data/0, offset, size, stride, requires_grad, hooks)``."""
    pid = (b"(X\x07\x00\x00\x00storagectorch\n" + storage + b"\nX\x01\x00\x00\x000X\x03\x00\x00\x00cpu"
           + b"J" + numel.to_bytes(4, "little") + b"tQ")
    return (b"ctorch._utils\n_rebuild_tensor_v2\n(" + pid + b"J" + offset.to_bytes(4, "little", signed=True)
            + _ints(size) + _ints(stride) + requires_grad + b"ccollections\nOrderedDict\n)R" + hooks + b"tR")


class _Evil:
    def __init__(self, fn, *args) -> None:
        self.fn, self.args = fn, args

    def __reduce__(self):
        return self.fn, self.args


SOFTMAX = "torch.softmax(argument_1, 1)"

LEAKY = "torch.leaky_relu(argument_1, 0.20000000000000001)"

SOFTPLUS = "torch.softplus(argument_1, 2., 10.)"

RELU = "torch.relu(argument_1)"

_CHAIN = "(_4).forward((_3).forward((_2).forward(_6, ), ), )"

_M = b"c__torch__.torch.nn.modules.container\nSequential\n"  # GLOBAL of the root's class


@pytest.fixture(scope="module")
def traced(tmp_path_factory) -> Path:
    """A traced Sequential holding every activation kind (code as torch.jit.trace writes it)."""
    path = tmp_path_factory.mktemp("ts") / "traced.pt"
    # traced in a fresh process: TorchScript mangles the class names of modules traced earlier in the
    # same process (``___torch_mangle_N``), and the code edits below match the unmangled text
    script = ("import warnings, torch; from torch import nn; warnings.simplefilter('ignore'); "
              "m = nn.Sequential(nn.Linear(3, 2), nn.Softmax(dim=1), nn.LeakyReLU(0.2), "
              "nn.Softplus(beta=2.0, threshold=10.0), nn.ReLU(), nn.Identity()); "
              f"torch.jit.save(torch.jit.trace(m, torch.randn(2, 3)), {str(path)!r})")
    subprocess.run([sys.executable, "-c", script], check=True)
    return path


# ------------------------------------------------------------------------------- archives that load
@pytest.mark.parametrize("mode", ["trace", "script"])
@pytest.mark.parametrize("name", list(DECODERS))
def test_real_archives_round_trip_exactly(tmp_path, name, mode):
    torch.manual_seed(0)
    eager = DECODERS[name]().eval()
    path = _save(eager, tmp_path / f"{name}_mlp.pt", mode, eager[0].in_features)
    rebuilt = eager_from_archive(path)
    assert not isinstance(rebuilt, torch.jit.ScriptModule) and isinstance(rebuilt, nn.Sequential)
    reference = _reference(path)
    x = torch.randn(257, eager[0].in_features) * 3
    assert torch.equal(rebuilt(x), reference(x))
    assert torch.equal(rebuilt(x), eager(x))
    assert rebuilt.state_dict().keys() == reference.state_dict().keys()
    assert not rebuilt.training and [type(m) for m in rebuilt.modules()] == [type(m) for m in eager.modules()]
    assert torch.equal(load_torchscript(path)(x), rebuilt(x))


def test_training_mode_and_single_layer(tmp_path):
    layer = nn.Linear(5, 3)  # a bare layer (no Sequential) in training mode
    path = _save(layer, tmp_path / "lin.pt", "trace", 5)
    rebuilt = eager_from_archive(path)
    x = torch.randn(4, 5)
    assert isinstance(rebuilt, nn.Linear) and rebuilt.training and torch.equal(rebuilt(x), _reference(path)(x))


@pytest.mark.parametrize("beta, threshold", [(0.5, 20.0), (1.0, 1.5), (2.0, 10.0)])
def test_softplus_settings_come_from_the_archive(tmp_path, beta, threshold):
    eager = nn.Sequential(nn.Linear(1, 1), nn.Softplus(beta=beta, threshold=threshold)).eval()
    with torch.no_grad():
        eager[0].weight.fill_(1.0)
        eager[0].bias.zero_()
    for mode in ("trace", "script"):
        path = tmp_path / f"sp_{mode}.pt"
        rebuilt = eager_from_archive(_save(eager, path, mode, 1))
        x = torch.tensor([[-3.0], [0.0], [0.5], [1.0], [2.0], [4.0], [8.0], [12.0]], dtype=torch.float64)
        want = torch.where(beta * x > threshold, x, torch.log1p(torch.exp(beta * x)) / beta)  # float64 by hand
        torch.testing.assert_close(rebuilt.double()(x), want, rtol=1e-12, atol=1e-12)


def test_the_untouched_archive_loads_with_its_settings(traced):
    """The base of every crafted archive below is accepted, settings read from its code's constants."""
    eager = eager_from_archive(traced)
    assert [type(m).__name__ for m in eager] == ["Linear", "Softmax", "LeakyReLU", "Softplus", "ReLU", "Identity"]
    assert eager[1].dim == 1 and eager[2].negative_slope == 0.2
    assert (eager[3].beta, eager[3].threshold) == (2.0, 10.0)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64, torch.float16, torch.bfloat16])
def test_float_storages_keep_their_dtype_and_values(tmp_path, dtype):
    g = torch.Generator().manual_seed(1)
    w = torch.randn(3, 4, generator=g).to(dtype)
    emb = torch.randn(2, 3, generator=g).to(dtype)
    got = tensors_from_archive(_save(_Buffers(w=w, emb=emb), tmp_path / "t.pt", "script"))
    assert set(got) == {"w", "emb"}
    for k, v in (("w", w), ("emb", emb)):
        assert got[k].dtype == dtype and torch.equal(got[k], v), k


@pytest.mark.parametrize("dtype", [torch.float64, torch.float16])
def test_linear_archives_in_other_float_dtypes(tmp_path, dtype):
    torch.manual_seed(2)
    m = nn.Sequential(nn.Linear(4, 3), nn.Tanh()).to(dtype)
    rebuilt = eager_from_archive(_save(m, tmp_path / "m.pt", "trace", 4, dtype))
    assert rebuilt[0].weight.dtype == dtype and torch.equal(rebuilt[0].weight, m[0].weight)
    assert torch.equal(rebuilt[0].bias, m[0].bias)


def test_tensors_from_archive_names_values_and_non_finite(tmp_path):
    path, module = _traced_two_levels(tmp_path, "ok.pt")
    got = tensors_from_archive(path)
    want = module.state_dict()
    assert list(got) == list(want) == ["0.weight", "0.bias", "1.0.weight", "1.0.bias"]
    assert all(torch.equal(got[k], want[k]) for k in want)
    eager = eager_from_archive(path)  # requires_grad as stored, per tensor
    assert [p.requires_grad for p in eager.parameters()] == [False, True, True, True]
    for fill, word in ((float("inf"), "inf"), (float("-inf"), "inf"), (float("nan"), "NaN")):
        bad, _ = _traced_two_levels(tmp_path, f"bad_{word}.pt", fill)
        for load in (tensors_from_archive, eager_from_archive):
            with pytest.raises(FileFormatError) as info:
                load(bad)
            assert str(bad) in str(info.value) and f"non-finite weights ({word}) in 1.0.bias" in str(info.value)
            assert "chain" not in str(info.value)  # reported as the weights, not as a structural problem


@pytest.mark.parametrize("byteorder,ok", [(b"little", True), (b"little\n", True), (None, True), (b"big", False),
                                          (b"littl", False)])
def test_byteorder_entry(traced, tmp_path, byteorder, ok):
    """Little-endian data (torch's ``byteorder`` entry, whitespace around it ignored, or no entry: older
    archives) is read; anything else is refused."""
    path = tmp_path / "b.pt"
    with zipfile.ZipFile(traced) as zin, zipfile.ZipFile(path, "w") as zout:
        prefix = zin.namelist()[0].split("/")[0]
        for info in zin.infolist():
            if info.filename != f"{prefix}/byteorder":
                zout.writestr(info, zin.read(info))
        if byteorder is not None:
            zout.writestr(f"{prefix}/byteorder", byteorder)
    if ok:
        assert torch.equal(eager_from_archive(path)[0].weight, eager_from_archive(traced)[0].weight)
    else:
        _refused(path, "big-endian tensor data")


def test_python_files_outside_the_code_folder_are_not_code(traced, tmp_path):
    """Only ``<name>/code/**.py`` is parsed: a .py elsewhere in the zip (a torch.package extra, say) is ignored."""
    path = _with_entries(traced, tmp_path / "x.pt", {"extra/evil.py": b"import os\nos.system('x')\n(((("})
    assert len(eager_from_archive(path)) == 6


# ------------------------------------------------------------------------------------ hostile code
def test_the_writer_archive_really_writes_when_run_the_trusted_way(tmp_path):
    """The test archives are real exploits: run the trusted way (in a subprocess), they write the file."""
    target = tmp_path / "victim"
    target.write_bytes(b"x" * 8)
    path = tmp_path / "opacity_mlp.pt"
    torch.jit.script(Writer(str(target))).save(str(path))
    code = f"import torch; torch.jit.load({str(path)!r})(torch.zeros(1, 4))"
    subprocess.run([sys.executable, "-c", code], check=True, timeout=60)
    assert target.read_bytes() == b"A" * 8


def test_forward_that_writes_a_file_is_refused_and_never_runs(tmp_path):
    target = tmp_path / "victim"
    path = tmp_path / "opacity_mlp.pt"
    torch.jit.script(Writer(str(target))).save(str(path))
    _refused(path, "Writer")
    with pytest.raises(FileFormatError, match="opacity_mlp.pt"):
        load_torchscript(path)
    assert not target.exists()


def test_setstate_that_writes_a_file_is_refused_and_never_runs(tmp_path):
    target = tmp_path / "victim"
    path = tmp_path / "cov_mlp.pt"
    torch.jit.script(SetState(str(target))).save(str(path))
    _refused(path, "__setstate__")
    with pytest.raises(FileFormatError, match=r"cov_mlp\.pt.*__setstate__"):
        tensors_from_archive(path)
    assert not target.exists()


def test_endless_loop_is_refused_without_hanging(tmp_path):
    path = tmp_path / "color_mlp.pt"
    torch.jit.script(Loop()).save(str(path))
    _refused(path, "Loop")


def test_writer_hidden_in_a_standard_layer_class_is_refused(tmp_path):
    """A genuine Sequential archive whose Tanh code is replaced by a file write: the class names are the
    supported ones, the code (read as text) is not."""
    target = tmp_path / "victim"
    src = _plain(tmp_path)
    name, code = _code_of(src, "Tanh")
    evil = code.replace("    return torch.tanh(argument_1)",
                        f"    t = torch.from_file({str(target)!r}, True, 8)\n    return torch.tanh(argument_1)")
    assert evil != code
    path = _patched(src, tmp_path / "opacity_mlp.pt", {name: evil.encode()})
    _refused(path, "torch.from_file")
    assert not target.exists()


def test_async_forward_is_refused(tmp_path):
    """``async def forward`` is not TorchScript (``torch.jit.load`` fails on it): a standard layer whose
    forward became async is refused, though its body is the genuine one."""
    src = _plain(tmp_path)
    name, code = _code_of(src, "Tanh")
    asynced = re.sub(r"(class Tanh\(Module\):.*?\n)  def forward\(", r"\1  async def forward(", code, count=1, flags=re.S)
    assert asynced != code
    _refused(_patched(src, tmp_path / "opacity_mlp.pt", {name: asynced.encode()}), "Tanh", "async def forward")


def test_loop_hidden_in_a_sequential_forward_is_refused(tmp_path):
    src = _plain(tmp_path)
    name, code = _code_of(src, "Sequential")
    looped = code.replace("    _4 = ", "    while True:\n      input = input\n    _4 = ")
    assert looped != code
    _refused(_patched(src, tmp_path / "loop.pt", {name: looped.encode()}), "while True", "not a plain chain")


def test_exported_extra_method_is_refused(tmp_path):
    class Extra(nn.Sequential):
        @torch.jit.export
        def extra(self) -> int:
            return 1

    path = _save(Extra(nn.Linear(4, 4), nn.ReLU()), tmp_path / "extra.pt", "script", 4)
    _refused(path, "defines extra")


def test_forward_reading_an_attribute_of_its_input_is_refused(tmp_path):
    """Only ``self.<name>`` reads a parameter: ``input.weight`` (an attribute of something else) is refused,
    not taken for ``self.weight``."""
    src = _plain(tmp_path)
    name, code = _code_of(src, "Linear")
    other = code.replace("weight = self.weight", "weight = input.weight")
    assert other != code
    _refused(_patched(src, tmp_path / "attr.pt", {name: other.encode()}), "input.weight", "not a plain chain")


@pytest.mark.parametrize("old,new", [
    (_CHAIN, "(_4).forward((_3).forward((_3).forward((_2).forward(_6, ), ), ), )"),  # a layer applied twice
    (_CHAIN, "(_4).forward((_2).forward((_3).forward(_6, ), ), )"),  # two layers swapped
    ("(_1).forward((_0).forward(input, ), )", "(_1).forward((_0).forward(input, ), input)"),  # a second input
    ("(_1).forward((_0).forward(input, ), )", "(_1).forward((_0).forward(_1, ), )"),  # not fed the input
    ("return _7", "return _6"),  # the last layers dropped
])
def test_sequential_chain_refusals(traced, tmp_path, old, new):
    _refused(_edited(traced, tmp_path / "c.pt", old, new),
             "the root Sequential (Sequential) whose forward is not the chain of its submodules "
             "['0', '1', '2', '3', '4', '5'] in order")


@pytest.mark.parametrize("old,new,what", [
    # activations: constants beyond the layer's own settings, settings that are not constants
    (RELU, "torch.relu(argument_1, 2)", ["4 (ReLU) whose forward passes [2] to relu"]),
    (RELU, "torch.relu(argument_1, True)", None),  # the functional helper's inplace flag is fine
    (SOFTMAX, "torch.softmax(argument_1, 1, 2, 6)", ["(Softmax) with a dtype argument 6"]),
    (SOFTMAX, "torch.softmax(argument_1, 1, 2, None, None)", ["(Softmax) with a dtype argument None"]),
    (SOFTMAX, "torch.softmax(argument_1, 1.5)", ["(Softmax) whose forward does not give dim as a constant"]),
    (SOFTMAX, "torch.softmax(argument_1)", ["(Softmax) whose forward does not give dim as a constant"]),
    (LEAKY, "torch.leaky_relu(argument_1, 0.2, False, 1)", ["(LeakyReLU) whose forward passes [0.2, False, 1]"]),
    (LEAKY, "torch.leaky_relu(argument_1, True)", ["does not give negative_slope as a constant"]),
    (SOFTPLUS, "torch.softplus(argument_1, 2.)", ["(Softplus) whose forward passes [2.0]"]),
    (SOFTPLUS, "torch.softplus(argument_1, 2., 10., 1.)", ["(Softplus) whose forward passes [2.0, 10.0, 1.0]"]),
    (SOFTPLUS, 'torch.softplus(argument_1, 2., "10")', ["does not give threshold as a constant"]),
    (SOFTPLUS, 'torch.softplus(argument_1, "2", 10.)', ["does not give beta as a constant"]),
    # the op called must be the layer's own, as torch.<op> or the scripted functional helper
    (RELU, "torch.tanh(argument_1)", ["(ReLU) whose forward calls torch.tanh"]),
    (RELU, "__torch__.evil.relu(argument_1)", ["(ReLU) whose forward calls __torch__.evil.relu"]),
    (RELU, "torch.relu(self.x)", ["(ReLU) whose forward is not one call of ['relu', 'relu_'] on its input"]),
    (RELU, "argument_1", ["(ReLU) whose forward is not one call"]),
    # Linear and Identity
    ("torch.linear(input, weight, bias)", "torch.linear(input, bias, weight)",
     ["0 (Linear) whose forward is not torch.linear(input, self.weight, self.bias)"]),
    ("NoneType:\n    return None", "NoneType:\n    return 1", ["5 (Identity) whose forward does not return its input"]),
    # the forward's shape: signature, statements, return, expressions
    ("argument_1: Tensor) -> Tensor:\n    return torch.relu",
     "argument_1: Tensor, b: Tensor) -> Tensor:\n    return torch.relu", ["4.forward with the signature (self, argument_1, b)"]),
    ("argument_1: Tensor) -> Tensor:\n    return torch.relu",
     "argument_1: Tensor=None) -> Tensor:\n    return torch.relu", ["4.forward with the signature"]),
    ("input = torch.leaky_relu", "input, b = torch.leaky_relu", ["2.forward with the statement 'input, b = torch.leaky_relu"]),
    ("    return input\nclass Softplus", "    input\nclass Softplus", ["2.forward that does not end in a return of its result"]),
    (RELU, "torch.relu(argument_1 + 1)", ["4.forward with the expression 'argument_1 + 1'"]),
    (RELU, "torch.relu(argument_1, inplace=False)", ["4.forward with the expression"]),
    (RELU, "torch.relu(-argument_1)", ["4.forward with the expression"]),
    # classes and names
    ("class ReLU(Module)", "class ReLU2(Module)", ["no code for the class __torch__.torch.nn.modules.activation.ReLU"]),
    ("return torch.relu(argument_1)\n", "return torch.relu(argument_1)\n  def __len__(self) -> int:\n    return 1\n", None),
])
def test_code_text_refusals(traced, tmp_path, old, new, what):
    path = _edited(traced, tmp_path / "crafted.pt", old, new)
    if what is None:
        assert isinstance(eager_from_archive(path)[4], nn.ReLU)
    else:
        _refused(path, *what)


def test_a_class_with_len_but_no_forward_is_refused(traced, tmp_path):
    """``__len__`` alone passes the method check; the missing forward is then named."""
    path = _edited(traced, tmp_path / "crafted.pt", "def forward(self: __torch__.torch.nn.modules.activation.ReLU",
                   "def __len__(self: __torch__.torch.nn.modules.activation.ReLU")
    _refused(path, "4 (ReLU) without a forward method")


@pytest.mark.parametrize("extra,what", [
    ("def helper(x: Tensor) -> Tensor:\n  return torch.save(x)\n", "that calls torch.save"),
    ("def helper(x: Tensor) -> Tensor:\n  return __torch__.nowhere.f(x)\n",
     "that uses __torch__.nowhere.f, which the archive does not define"),
    ("def helper(x: Tensor) -> Tensor:\n  return os.getcwd(x)\n", "that uses os.getcwd"),
    ("def helper(x: Tensor) -> Tensor:\n  return eval(x)\n", "that calls eval"),
    ("def helper(x: Tensor) -> Tensor:\n  y = torch.relu(x)\n  return y\n", None),  # locals and safe ops pass
    ("def helper(x: Tensor) -> Tensor:\n  return int(getattr(x, \"y\"))\n", None),  # TorchScript builtins pass
])
def test_names_in_unused_code_are_checked_too(traced, tmp_path, extra, what):
    """Every function of the code files is checked, also one no forward calls."""
    path = _edited(traced, tmp_path / "crafted.pt", "class Softmax(Module)", extra + "class Softmax(Module)")
    if what is None:
        assert len(eager_from_archive(path)) == 6
    else:
        _refused(path, "code (__torch__.torch.nn.modules.activation)", what)


def test_code_that_is_not_python_is_refused(traced, tmp_path):
    path = _edited(traced, tmp_path / "crafted.pt", "class Softmax(Module)", "class Softmax(Module")
    _refused(path, "code file", "activation.py", "that is not TorchScript source (SyntaxError)")


# ---------------------------------------------------------------------------------------- pickles
@pytest.mark.parametrize("fn, args, named", [
    (os.system, ("touch {target}",), "system"),
    (eval, ("open({target!r}, 'w').write('x')",), "builtins.eval"),
    (subprocess.check_call, (["touch", "{target}"],), "subprocess.check_call"),
    (getattr, ("x", "upper"), "builtins.getattr"),
])
def test_pickle_naming_foreign_globals_is_refused_and_never_unpickled(tmp_path, fn, args, named):
    target = tmp_path / "victim"
    args = tuple(a.format(target=str(target)) if isinstance(a, str) else
                 [x.format(target=str(target)) for x in a] if isinstance(a, list) else a for a in args)
    payload = pickle.dumps({"training": False, "0": _Evil(fn, *args)}, protocol=2, fix_imports=False)
    path = _patched(_plain(tmp_path), tmp_path / "opacity_mlp.pt", {"/data.pkl": payload})
    _refused(path, named, "global")
    with pytest.raises(FileFormatError, match=named):
        tensors_from_archive(path)
    assert not target.exists()


def test_constants_are_restricted_and_an_archive_holds_one_tree(traced, tmp_path):
    target = tmp_path / "victim"
    payload = pickle.dumps(_Evil(os.system, f"touch {target}"), protocol=2)
    path = _patched(_plain(tmp_path), tmp_path / "c.pt", {"/constants.pkl": payload})
    _refused(path, "system")
    assert not target.exists()
    _refused(_with_entries(traced, tmp_path / "c.pt", {"constants.pkl": pickle.dumps((1.0,), protocol=2)}),
             "tensor constants used by its code (a decoder has none)")
    assert len(eager_from_archive(_with_entries(traced, tmp_path / "e.pt", {"constants.pkl": pickle.dumps(())}))) == 6
    with zipfile.ZipFile(traced) as z:
        pkl = next(z.read(n) for n in z.namelist() if n.endswith("/data.pkl"))
    path = _with_entries(traced, tmp_path / "two.pt", {})
    with zipfile.ZipFile(path, "a") as z:
        z.writestr("other/data.pkl", pkl)
    _refused(path, "several module trees")


@pytest.mark.parametrize("after, what", [(b"ctorch\nFloatStorage\n", "a pickled BUILD on a storage type"),
                                         (b"Q", "a pickled BUILD on a storage record")])
def test_pickled_build_on_storage_objects_is_refused(tmp_path, after, what):
    """pickle's BUILD updates an object's ``__dict__`` directly (a frozen dataclass does not stop it): a
    storage type renamed that way ('LongStorage' called 'FloatStorage') would pass the float-only check."""
    src = _save(nn.Sequential(nn.Linear(3, 2)), tmp_path / "a.pt", "trace", 3)
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
    src = _save(nn.Sequential(nn.Linear(3, 2)), tmp_path / "a.pt", "trace", 3)
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


@pytest.mark.parametrize("pkl,what", [
    (_M + b"K\x01\x85\x81.", "object of class __torch__.torch.nn.modules.container.Sequential built with arguments"),
    (b"K\x01.", " is a pickled int, not a TorchScript module"),
    (_M + b")\x81K\x01b.", "module  (__torch__.torch.nn.modules.container.Sequential) whose state is not a plain dict"),
    (_M + b")\x81}K\x01K\x02sb.", "whose state is not a plain dict"),  # a non-string key
    (_M + b")\x81}X\x01\x00\x00\x00xK\x01\x85sb.", "attribute .x holding a tuple"),
    (b"K\x01Q.", "an unexpected persistent id '1'"),
    (b"(X\x07\x00\x00\x00storagectorch\nFloatStorage\nX\x01\x00\x00\x00aX\x03\x00\x00\x00cpuK\x01tQ.",
     "an unexpected persistent id"),  # a storage key that is not a number
    (b"cbuiltins\neval\n.", "a pickled reference to the global 'builtins.eval'"),
    (b"c__torch__.a-b\nM\n.", "a pickled reference to the global '__torch__.a-b.M'"),  # not identifiers
])
def test_pickle_refusals(traced, tmp_path, pkl, what):
    _refused(_with_entries(traced, tmp_path / "p.pt", {"data.pkl": b"\x80\x02" + pkl}), what)


# ------------------------------------------------------------------------------- layers and state
def test_an_unsupported_layer_is_refused_naming_it(tmp_path):
    _refused(_save(nn.Sequential(nn.Linear(4, 4), nn.GELU()), tmp_path / "gelu.pt", "trace", 4), "GELU")


@pytest.mark.parametrize("global_,what", [
    (b"c__torch__.torch.nn.modules.activation\nReLU6\n",
     "4 of type __torch__.torch.nn.modules.activation.ReLU6 (supported: Sequential of Linear, Identity, ReLU, "
     "Tanh, Sigmoid, SiLU, Softmax, LeakyReLU, Softplus)"),
    (b"c__torch__.mylib\nReLU\n", "4 of type __torch__.mylib.ReLU (supported"),  # a kind, but not torch.nn's
    (b"c__torch__.torch.nn.modules.activation.___torch_mangle_3\nReLU\n",
     "no code for the class __torch__.torch.nn.modules.activation.___torch_mangle_3.ReLU"),  # mangled: a kind
])
def test_layer_kind_is_read_from_the_torch_nn_class_name(traced, tmp_path, global_, what):
    with zipfile.ZipFile(traced) as z:
        pkl = next(z.read(n) for n in z.namelist() if n.endswith("/data.pkl"))
    old = b"c__torch__.torch.nn.modules.activation\nReLU\n"
    assert pkl.count(old) == 1
    _refused(_with_entries(traced, tmp_path / "k.pt", {"data.pkl": pkl.replace(old, global_)}), what)


@pytest.mark.parametrize("dim", [b"K\x00", b"K\x01"])
def test_a_stored_softmax_dim_is_an_unexpected_attribute(traced, tmp_path, dim):
    """torch.jit keeps Softmax's dim in the code only (a Final constant); a dim in the pickled state,
    equal to the code's (1) or not, is refused like any attribute a decoder does not hold."""
    with zipfile.ZipFile(traced) as z:
        pkl = next(z.read(n) for n in z.namelist() if n.endswith("/data.pkl"))
    crafted, n = re.subn(rb"(activation\nSoftmax\nq.\)\x81\}\()", lambda m: m.group(1) + b"X\x03\x00\x00\x00dim" + dim, pkl)
    assert n == 1
    _refused(_with_entries(traced, tmp_path / "d.pt", {"data.pkl": crafted}), "1 (Softmax) with unexpected attributes ['dim']")


@pytest.mark.parametrize("make,mode,what", [
    (lambda: _with(nn.Sequential(nn.Linear(3, 2)), foo=3), "script",
     "the root module (Sequential) with unexpected attributes ['foo']"),
    (lambda: nn.Sequential(nn.Linear(3, 2), _with(nn.ReLU(), b=torch.zeros(1))), "trace", "1 (ReLU) with tensors ['b']"),
    (lambda: nn.Sequential(nn.Linear(3, 2), _with(nn.ReLU(), child=nn.Identity())), "trace",
     "1 (ReLU) with submodules ['child']"),
    (lambda: nn.Sequential(_with(nn.Linear(3, 2), scale=torch.ones(2))), "trace",
     "0 (Linear) holding ['bias', 'scale', 'weight']; expected weight[, bias]"),
    (lambda: _with(nn.Sequential(nn.Linear(3, 2)), x=torch.ones(2)), "trace",
     "the root Sequential (Sequential) holding ['0', 'x']; expected submodules '0'..'n-1'"),
    (lambda: nn.Sequential(_linear(bias=torch.zeros(2, dtype=torch.float64))), "script",
     "0 (Linear) with weight torch.float32 and bias torch.float64"),
    (lambda: nn.Sequential(_linear(bias=torch.zeros(3))), "script",
     "0 (Linear) with weight [2, 3] and bias [3]; expected [out, in] and [out]"),
    (lambda: nn.Sequential(_linear(weight=torch.zeros(2, 3, 1))), "script", "0 (Linear) with weight [2, 3, 1] and bias [2]"),
])
def test_module_state_refusals(tmp_path, make, mode, what):
    """Modules whose pickled state is not what their kind holds (extra attributes, tensors, children,
    shapes, dtypes), written by torch.jit itself."""
    path = tmp_path / "crafted.pt"
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        module = make()
        torch.jit.save(torch.jit.trace(module, torch.randn(2, 3)) if mode == "trace" else torch.jit.script(module), str(path))
    _refused(path, what)


# --------------------------------------------------------------------------------- tensor records
def test_strided_records_read_their_elements_and_one_past_the_storage_is_refused(tmp_path):
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


@pytest.mark.parametrize("pkl,what", [
    # the base archive's data/0 holds 6 float32 (its Linear's weight); every record below points at it
    (_record((6,), (1,), requires_grad=b"K\x01"), "a malformed tensor record"),  # 1 is not a bool
    (_record((6,), (1,), hooks=b"K\x01K\x02s"), "a malformed tensor record"),  # backward hooks
    (_record((2,), (1,), offset=4), "is a pickled _TensorRecord"),  # last element data/0[5]: inside
    (_record((2,), (1,), offset=5), "a tensor of shape [2] that reaches past its storage data/0"),
    (_record((2, 2), (3, 1), offset=1), "is a pickled _TensorRecord"),  # last element 1 + 3 + 1 = 5
    (_record((2, 2), (4, 1), offset=1), "a tensor of shape [2, 2] that reaches past its storage data/0"),
    (_record((7,), (0,)), "a tensor of shape [7] larger than its storage data/0"),
    (_record((0,), (1,), offset=100), "is a pickled _TensorRecord"),  # empty: no element to reach
    (b"(" + _record((6,), (1,)) + _record((3,), (1,), storage=b"DoubleStorage", numel=3) + b"t",
     "storage data/0 is referenced with two dtypes or sizes"),
    (b"(" + _record((6,), (1,)) + _record((5,), (1,), numel=5) + b"t", "storage data/0 is referenced with two dtypes or sizes"),
    (_record((6,), (1,)) + b"}b", "a pickled BUILD on a tensor"),
])
def test_tensor_record_refusals_and_bounds(traced, tmp_path, pkl, what):
    _refused(_with_entries(traced, tmp_path / "t.pt", {"data.pkl": b"\x80\x02" + pkl + b"."}), what)


@pytest.mark.parametrize("dtype", [torch.int64, torch.int32, torch.int16, torch.int8, torch.uint8, torch.bool,
                                   torch.complex64, torch.complex128])
def test_non_float_storages_are_refused_naming_the_dtype(tmp_path, dtype):
    t = torch.ones(3).to(dtype)
    with pytest.raises(FileFormatError, match=rf"t\.pt: TorchScript archive refused .*a non-float tensor \({dtype}\); "
                                              r"decoders hold floating-point weights only"):
        tensors_from_archive(_save(_Buffers(t=t), tmp_path / "t.pt", "script"))


def test_archive_container_refusals_name_file_and_cause(tmp_path):
    src = tmp_path / "lin.pt"
    net = nn.Sequential(nn.Linear(2, 3))
    torch.jit.trace(net, torch.zeros(1, 2)).save(str(src))
    with zipfile.ZipFile(src) as z:
        pkl = z.read(next(n for n in z.namelist() if n.endswith("/data.pkl")))
    assert torch.equal(eager_from_archive(src)[0].weight, net[0].weight)
    cases = [
        ({"/data/0": None}, "b.pt", "refused (nothing in it was run): no entry 'lin/data/0'"),
        ({"/data/0": bytes(20)}, "c.pt", "storage data/0 holds 20 bytes, its record needs 24"),
        ({"/data.pkl": pkl.replace(b"K\x00(K\x03K\x02t", b"J\xff\xff\xff\xff(K\x03K\x02t")}, "d.pt", "a malformed tensor record"),
        ({"/data.pkl": pkl.replace(b"(K\x03K\x02t(K\x02K\x01t", b"(K\x03K\x02t(K\x02t")}, "e.pt", "a malformed tensor record"),
        ({"/data.pkl": None}, "f.pt", "no <name>/data.pkl (not a TorchScript or torch.save zip archive)"),
    ]
    for edit, name, words in cases:
        with pytest.raises(FileFormatError, match=rf"{name}: ") as e:
            eager_from_archive(_patched(src, tmp_path / name, edit))
        assert words in str(e.value), (name, str(e.value))
    torch.save(net.state_dict(), tmp_path / "sd.pt")
    with pytest.raises(FileFormatError, match=r"sd.pt: .*no code/ folder \(not a TorchScript archive; a torch.save file\?\)"):
        eager_from_archive(tmp_path / "sd.pt")


def test_not_torchscript(tmp_path):
    sd = tmp_path / "state.pt"
    torch.save(DECODERS["opacity"]().state_dict(), sd)
    _refused(sd, "TorchScript")
    junk = tmp_path / "junk.pt"
    junk.write_bytes(b"\x00not a zip" * 10)
    _refused(junk, "not a zip")
    with pytest.raises(FileFormatError, match="no such file"):
        eager_from_archive(tmp_path / "missing.pt")
    trunc = tmp_path / "trunc.pt"
    trunc.write_bytes(_plain(tmp_path).read_bytes()[:-300])
    _refused(trunc)


# ------------------------------------------------------------------------------------------ bounds
def test_entry_count_bound_is_4096(tmp_path):
    src = _save(nn.Sequential(nn.Linear(3, 2)), tmp_path / "a.pt", "trace", 3)
    ok = eager_from_archive(_with_extra_entries(src, tmp_path / "ok.pt", 4096))  # at the bound: read
    assert isinstance(ok, nn.Sequential)
    with pytest.raises(FileFormatError, match=r"over\.pt: TorchScript archive refused .*4097 zip entries \(at most 4096"):
        eager_from_archive(_with_extra_entries(src, tmp_path / "over.pt", 4097))


@pytest.mark.parametrize("levels,ok", [(32, True), (33, False)])
def test_nesting_bound_is_32_levels(tmp_path, levels, ok):
    """A Linear under 32 nested Sequentials (depth 32) is read; one level more is refused, naming where."""
    module: nn.Module = nn.Linear(3, 2)
    for _ in range(levels):
        module = nn.Sequential(module)
    path = tmp_path / "n.pt"
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        torch.jit.save(torch.jit.trace(module, torch.randn(2, 3)), str(path))
    if ok:
        rebuilt = eager_from_archive(path)
        x = torch.randn(5, 3)
        assert torch.equal(rebuilt(x), module(x))
        got = rebuilt
        for _ in range(levels):
            got = got[0]
        assert torch.equal(got.weight, module.get_submodule(".".join(["0"] * levels)).weight)
    else:
        _refused(path, "modules nested deeper than 32 (or a cycle) at " + ".".join(["0"] * 33))


def test_tensor_dims_bound_is_8(tmp_path):
    t8 = torch.arange(2.0).reshape([1] * 7 + [2])
    got = tensors_from_archive(_save(_Buffers(t=t8), tmp_path / "d8.pt", "script"))
    assert got["t"].shape == t8.shape and torch.equal(got["t"], t8)
    with pytest.raises(FileFormatError, match=r"d9\.pt: TorchScript archive refused .*a malformed tensor record"):
        tensors_from_archive(_save(_Buffers(t=torch.zeros([1] * 9)), tmp_path / "d9.pt", "script"))


def test_pickle_bound_is_16_mib(tmp_path):
    src = _save(nn.Sequential(nn.Linear(3, 2)), tmp_path / "a.pt", "trace", 3)
    with zipfile.ZipFile(src) as z:
        size = len(z.read("a/data.pkl"))
    # bytes after the pickle's STOP opcode are never read by the unpickler: only the entry's size matters
    ok = _padded(src, tmp_path / "ok.pt", "/data.pkl", b"\0" * ((16 << 20) - size))
    assert isinstance(eager_from_archive(ok), nn.Sequential)
    over = _padded(src, tmp_path / "over.pt", "/data.pkl", b"\0" * ((16 << 20) + 1 - size))
    with pytest.raises(FileFormatError, match=r"over\.pt: .*entry 'a/data\.pkl' of 16777217 bytes \(at most 16777216\)"):
        eager_from_archive(over)


def test_code_bound_is_4_mib_for_all_code_files_together(tmp_path, traced, monkeypatch):
    src = _save(nn.Sequential(nn.Linear(3, 2)), tmp_path / "a.pt", "trace", 3)
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
    # each code file fits a lower bound, their total does not
    with zipfile.ZipFile(traced) as z:
        sizes = [i.file_size for i in z.infolist() if "/code/" in i.filename and i.filename.endswith(".py")]
    assert len(sizes) >= 3
    monkeypatch.setattr(ts, "_MAX_CODE_BYTES", sum(sizes))
    assert len(eager_from_archive(traced)) == 6  # exactly at the bound: accepted
    monkeypatch.setattr(ts, "_MAX_CODE_BYTES", sum(sizes) - 1)  # each file fits, their total does not
    _refused(traced, f"over {sum(sizes) - 1} bytes of code")


def test_total_size_bound_is_1_gib_of_uncompressed_entries(tmp_path, monkeypatch):
    src = _save(nn.Sequential(nn.Linear(3, 2)), tmp_path / "a.pt", "trace", 3)
    with zipfile.ZipFile(src) as z:
        used = sum(i.file_size for i in z.infolist())
    ok = _declaring(src, tmp_path / "ok.pt", (1 << 30) - used)
    with zipfile.ZipFile(ok) as z:
        assert sum(i.file_size for i in z.infolist()) == 1 << 30
    assert isinstance(eager_from_archive(ok), nn.Sequential)
    with pytest.raises(FileFormatError, match=r"over\.pt: .*an uncompressed size over 1073741824 bytes"):
        eager_from_archive(_declaring(src, tmp_path / "over.pt", (1 << 30) + 1 - used))
    # every entry fits a lower bound, their total does not
    net = nn.Sequential(nn.Linear(3, 2))
    src = _save(net, tmp_path / "lin.pt", "trace", 3)
    with zipfile.ZipFile(src) as z:
        sizes = [i.file_size for i in z.infolist()]
    assert max(sizes) < sum(sizes) - 1
    monkeypatch.setattr(ts, "_MAX_TOTAL_BYTES", sum(sizes))
    assert torch.equal(ts.eager_from_archive(src)[0].weight, net[0].weight)  # exactly at the bound
    monkeypatch.setattr(ts, "_MAX_TOTAL_BYTES", sum(sizes) - 1)  # every entry fits, their total does not
    with pytest.raises(FileFormatError, match=rf"lin.pt: .*an uncompressed size over {sum(sizes) - 1} bytes"):
        ts.eager_from_archive(src)
    # a compressed entry counts at its uncompressed size
    monkeypatch.setattr(ts, "_MAX_TOTAL_BYTES", 1 << 20)
    bomb = tmp_path / "bomb.pt"
    with zipfile.ZipFile(src) as zin, zipfile.ZipFile(bomb, "w", zipfile.ZIP_DEFLATED) as zout:
        for info in zin.infolist():
            zout.writestr(info.filename, zin.read(info))
        zout.writestr("lin/extra/zeros", bytes(2 << 20))
    assert bomb.stat().st_size < 64 << 10
    _refused(bomb, "uncompressed size")
