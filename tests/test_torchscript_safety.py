"""Loading TorchScript decoder files never runs code from them (issue 12, section 1).

Real archives (``torch.jit.trace`` / ``torch.jit.script`` of the families' decoder shapes) round-trip
to eager modules with the TorchScript module's exact outputs; malicious archives (a ``forward`` or a
``__setstate__`` that writes a file, an endless loop, pickles naming ``os.system`` & co., zip bombs)
are refused with a FileFormatError naming the file, nothing is written and nothing hangs.
"""

from __future__ import annotations

import contextlib
import os
import pickle
import re
import signal
import subprocess
import sys
import warnings
import zipfile
from pathlib import Path

import pytest
import torch
from torch import nn

import controlgs_adapter.formats.torchscript as ts
from controlgs_adapter.formats.backbone import load_torchscript, load_torchscript_tensors
from controlgs_adapter.backends.octree_gs import load_octree_gs_dir
from controlgs_adapter.backends.models.reference_model import NeuralGaussianModel
from controlgs_adapter.backends.scaffold_io import load_scaffold_dir, save_scaffold_dir
from controlgs_adapter.errors import FileFormatError
from controlgs_adapter.formats.torchscript import eager_from_archive, tensors_from_archive

pytestmark = pytest.mark.filterwarnings("ignore::DeprecationWarning")  # torch.jit.*: the format under test


@pytest.fixture(autouse=True)
def _no_hang():
    """Every test here must finish in seconds: an archive whose code loops forever must not be run."""
    def _timeout(signum, frame):
        raise TimeoutError("the load hung (code from the archive ran?)")
    old = signal.signal(signal.SIGALRM, _timeout)
    signal.alarm(20)
    yield
    signal.alarm(0)
    signal.signal(signal.SIGALRM, old)


_JIT_ALLOWED = [False]


@contextlib.contextmanager
def _jit_allowed():
    """Where the test itself loads an archive it trusts (reference outputs, ``trust_code=True``)."""
    _JIT_ALLOWED[0] = True
    try:
        yield
    finally:
        _JIT_ALLOWED[0] = False


@pytest.fixture(autouse=True)
def _no_jit_import(monkeypatch):
    """Without ``trust_code`` torch's TorchScript importer is never entered (it is what runs ``__setstate__``)."""
    for name in ("import_ir_module", "import_ir_module_from_buffer"):
        original = getattr(torch._C, name)

        def guarded(*args, _original=original, **kwargs):
            if not _JIT_ALLOWED[0]:
                raise AssertionError("torch's TorchScript importer was called without trust_code=True")
            return _original(*args, **kwargs)
        monkeypatch.setattr(torch._C, name, guarded)


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


F, K = 32, 10
DECODERS = {  # Scaffold-GS / Octree-GS / HAC decoder shapes (feat + view 3 [+ dist 1] [+ appearance])
    "opacity": lambda: nn.Sequential(nn.Linear(F + 3, F), nn.ReLU(True), nn.Linear(F, K), nn.Tanh()),
    "opacity_dist": lambda: nn.Sequential(nn.Linear(F + 4, F), nn.ReLU(True), nn.Linear(F, K), nn.Tanh()),
    "cov": lambda: nn.Sequential(nn.Linear(F + 3, F), nn.ReLU(True), nn.Linear(F, 7 * K)),
    "color": lambda: nn.Sequential(nn.Linear(F + 3 + 32, F), nn.ReLU(True), nn.Linear(F, 3 * K), nn.Sigmoid()),
    "feature_bank": lambda: nn.Sequential(nn.Linear(4, F), nn.ReLU(True), nn.Linear(F, 3), nn.Softmax(dim=1)),
    "hac_opacity": lambda: nn.Sequential(nn.Linear(54, 50), nn.ReLU(True), nn.Linear(50, K), nn.Tanh()),
    "nested": lambda: nn.Sequential(nn.Linear(6, 8), nn.LeakyReLU(0.1), nn.Sequential(nn.Linear(8, 8, bias=False),
                                    nn.SiLU()), nn.Linear(8, 5), nn.Softplus(beta=2.0, threshold=10.0),
                                    nn.Identity(), nn.Softmax(-1)),
}


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


class _Embedding(nn.Module):  # Scaffold-GS's scene/embedding.py wrapper
    def __init__(self) -> None:
        super().__init__()
        self.embedding = nn.Embedding(7, 32)

    def forward(self, idx: torch.Tensor) -> torch.Tensor:
        return self.embedding(idx)


def test_appearance_embedding_tensors(tmp_path):
    path = tmp_path / "embedding_appearance.pt"
    torch.jit.trace(_Embedding(), torch.zeros(3, dtype=torch.long)).save(str(path))
    got = load_torchscript_tensors(path)
    want = _reference(path).state_dict()
    assert got.keys() == want.keys() == {"embedding.weight"} and torch.equal(got["embedding.weight"], want["embedding.weight"])
    with _jit_allowed():
        trusted = load_torchscript_tensors(path, trust_code=True)
    assert torch.equal(trusted["embedding.weight"], want["embedding.weight"])


# ------------------------------------------------------------------------------------------------
# Malicious archives
# ------------------------------------------------------------------------------------------------

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


class SetState(nn.Module):
    """A scripted ``__setstate__`` (run by ``torch.jit.load`` itself) that writes ``target``."""

    def __init__(self, target: str) -> None:
        super().__init__()
        self.weight = nn.Parameter(torch.ones(4, 4))
        self.target = target

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return x @ self.weight

    @torch.jit.export
    def __getstate__(self) -> tuple[str, torch.Tensor, bool]:
        return (self.target, self.weight, self.training)

    @torch.jit.export
    def __setstate__(self, state: tuple[str, torch.Tensor, bool]) -> None:
        self.target = state[0]
        t = torch.from_file(self.target, True, 8, dtype=torch.uint8)
        self.weight = state[1] + t[:1].float().fill_(0)
        self.training = state[2]


class Loop(nn.Module):
    def __init__(self) -> None:
        super().__init__()
        self.lin = nn.Linear(4, 4)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        while True:
            x = x + 1
        return self.lin(x)


def _patched(src: Path, dst: Path, edit: dict[str, bytes | None], extra: dict[str, bytes] | None = None) -> Path:
    """A copy of the zip ``src`` with entries ending in a key of ``edit`` replaced (or dropped for None)."""
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


def _plain(tmp_path: Path) -> Path:
    return _save(DECODERS["opacity"](), tmp_path / "plain.pt", "trace", F + 3)


def _code_of(src: Path, cls: str) -> tuple[str, str]:
    """(entry name, text) of the code file of ``src`` that defines ``class <cls>`` (names may be mangled)."""
    with zipfile.ZipFile(src) as z:
        for name in z.namelist():
            if name.endswith(".py") and f"class {cls}(" in z.read(name).decode():
                return name, z.read(name).decode()
    raise AssertionError(f"no class {cls} in {src}")


def _refused(path: Path, *what: str) -> FileFormatError:
    with pytest.raises(FileFormatError) as info:
        eager_from_archive(path)
    msg = str(info.value)
    assert str(path) in msg, msg
    for w in what:
        assert w in msg, msg
    return info.value


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


def test_forward_that_skips_or_reorders_layers_is_refused(tmp_path):
    src = _plain(tmp_path)
    name, code = _code_of(src, "Sequential")
    reordered = code.replace("(_1).forward((_0).forward(input, ), )", "(_0).forward((_1).forward(input, ), )")
    assert reordered != code
    _refused(_patched(src, tmp_path / "order.pt", {name: reordered.encode()}), "chain of its submodules")


def test_exported_extra_method_is_refused(tmp_path):
    class Extra(nn.Sequential):
        @torch.jit.export
        def extra(self) -> int:
            return 1

    path = _save(Extra(nn.Linear(4, 4), nn.ReLU()), tmp_path / "extra.pt", "script", 4)
    _refused(path, "defines extra")


class _Evil:
    def __init__(self, fn, *args) -> None:
        self.fn, self.args = fn, args

    def __reduce__(self):
        return self.fn, self.args


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


def test_constants_pickle_is_restricted_too(tmp_path):
    target = tmp_path / "victim"
    payload = pickle.dumps(_Evil(os.system, f"touch {target}"), protocol=2)
    path = _patched(_plain(tmp_path), tmp_path / "c.pt", {"/constants.pkl": payload})
    _refused(path, "system")
    assert not target.exists()


def test_nan_weights_are_reported_as_such(tmp_path):
    dec = DECODERS["opacity"]()
    with torch.no_grad():
        dec[2].weight[0, 0] = float("nan")
    path = _save(dec, tmp_path / "opacity_mlp.pt", "trace", F + 3)
    err = _refused(path, "NaN", "2.weight")
    assert "chain" not in str(err)


def test_unsupported_layers_non_float_tensors_and_shapes(tmp_path):
    _refused(_save(nn.Sequential(nn.Linear(4, 4), nn.GELU()), tmp_path / "gelu.pt", "trace", 4), "GELU")
    lin = nn.Linear(4, 4)
    lin.register_buffer("steps", torch.zeros(3, dtype=torch.long))
    _refused(_save(nn.Sequential(lin, nn.ReLU()), tmp_path / "long.pt", "trace", 4), "non-float", "int64")
    src = _save(DECODERS["feature_bank"](), tmp_path / "fb.pt", "script", 4)
    name, code = _code_of(src, "Softmax")
    assert "_0(input, 1, 5, None, )" in code
    dtype = code.replace("_0(input, 1, 5, None, )", "_0(input, 1, 5, 7, )").encode()
    _refused(_patched(src, tmp_path / "dtype.pt", {name: dtype}), "Softmax", "dtype")


def test_tensor_records_reaching_past_their_storage_are_refused(tmp_path):
    src = _plain(tmp_path)
    with zipfile.ZipFile(src) as z:
        data = next(n for n in z.namelist() if n.endswith("/data/0"))
        short = z.read(data)[:100]
    _refused(_patched(src, tmp_path / "short.pt", {"/data/0": short}), "data/0")


def test_tensor_records_larger_than_their_storage_are_refused(tmp_path):
    """A stride-0 record declaring 2**40 elements would allocate terabytes when made contiguous."""
    src = _plain(tmp_path)
    with zipfile.ZipFile(src) as z:
        pkl = z.read("plain/data.pkl")
    huge = pkl.replace(b"K\x20K\x23t(K\x23K\x01t", b"\x8a\x06\x00\x00\x00\x00\x00\x01t(K\x00t", 1)
    assert huge != pkl  # weight [32, 35] with strides (35, 1) -> [2**40] with stride (0,)
    _refused(_patched(src, tmp_path / "huge.pt", {"/data.pkl": huge}), "larger than its storage")


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


def test_zip_bombs_and_oversized_pickles_are_refused(tmp_path, monkeypatch):
    src = _plain(tmp_path)
    many = _patched(src, tmp_path / "many.pt", {}, {f"extra/{i}": b"" for i in range(ts._MAX_ENTRIES + 1)})
    _refused(many, "zip entries")
    monkeypatch.setattr(ts, "_MAX_TOTAL_BYTES", 1 << 20)
    bomb = tmp_path / "bomb.pt"
    with zipfile.ZipFile(src) as zin, zipfile.ZipFile(bomb, "w", zipfile.ZIP_DEFLATED) as zout:
        for info in zin.infolist():
            zout.writestr(info.filename, zin.read(info))
        zout.writestr("plain/extra/zeros", bytes(2 << 20))
    assert bomb.stat().st_size < 64 << 10
    _refused(bomb, "uncompressed size")
    monkeypatch.setattr(ts, "_MAX_PICKLE_BYTES", 64)
    _refused(src, "data.pkl", "bytes")


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


# ------------------------------------------------------------------------------------------------
# Through the folder loaders
# ------------------------------------------------------------------------------------------------

def _scaffold_folder(tmp_path: Path) -> Path:
    torch.manual_seed(0)
    model = NeuralGaussianModel(20, feat_dim=8, n_offsets=3, appearance_dim=0)
    save_scaffold_dir(model, tmp_path / "model", iteration=7)
    return tmp_path / "model"


def test_scaffold_folder_with_a_malicious_decoder_fails_cleanly(tmp_path):
    folder = _scaffold_folder(tmp_path)
    loaded = load_scaffold_dir(folder)  # the clean folder loads, nothing run
    assert isinstance(loaded.mlp_opacity, nn.Sequential)
    target = tmp_path / "victim"
    evil = folder / "point_cloud" / "iteration_7" / "opacity_mlp.pt"
    torch.jit.script(Writer(str(target))).save(str(evil))
    with pytest.raises(FileFormatError, match=r"iteration_7.opacity_mlp\.pt.*refused"):
        load_scaffold_dir(folder)
    torch.jit.script(SetState(str(target))).save(str(evil))
    with pytest.raises(FileFormatError, match=r"opacity_mlp\.pt.*__setstate__"):
        load_scaffold_dir(folder)
    assert not target.exists()


def test_octree_folder_with_a_malicious_decoder_fails_cleanly(tmp_path):
    from test_backend_octree_gs import _arrays, _decoders, _write_dir  # noqa: PLC0415 - the family's folder writer

    folder = _write_dir(tmp_path / "scene", _arrays(2), _decoders(torch.Generator().manual_seed(2)))
    assert isinstance(load_octree_gs_dir(folder).mlp_cov, nn.Sequential)
    target = tmp_path / "victim"
    evil = folder / "point_cloud" / "iteration_30000" / "cov_mlp.pt"
    torch.jit.script(SetState(str(target))).save(str(evil))
    with pytest.raises(FileFormatError, match=r"cov_mlp\.pt.*__setstate__"):
        load_octree_gs_dir(folder)
    assert not target.exists()


def test_forward_reading_an_attribute_of_its_input_is_refused(tmp_path):
    """Only ``self.<name>`` reads a parameter: ``input.weight`` (an attribute of something else) is refused,
    not taken for ``self.weight``."""
    src = _plain(tmp_path)
    name, code = _code_of(src, "Linear")
    other = code.replace("weight = self.weight", "weight = input.weight")
    assert other != code
    _refused(_patched(src, tmp_path / "attr.pt", {name: other.encode()}), "input.weight", "not a plain chain")
