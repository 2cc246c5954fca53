"""Refusals and branches of pieces no other test reaches (issue 15, section 5): the TorchScript
archive reader's code-text checks, one crafted archive per refusal branch, each checked for the
library's error type, the file's name and what was found."""

from __future__ import annotations

import math
import subprocess
import sys
import warnings
import zipfile
from pathlib import Path

import pytest
import torch
from torch import nn

from controlgs_adapter.errors import FileFormatError
from controlgs_adapter.formats.torchscript import eager_from_archive

pytestmark = pytest.mark.filterwarnings("ignore::DeprecationWarning")  # torch.jit.*: the format under test


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


def _refused(path: Path, *what: str) -> str:
    with pytest.raises(FileFormatError) as info:
        eager_from_archive(path)
    msg = str(info.value)
    assert str(path) in msg and "refused" in msg, msg
    for w in what:
        assert w in msg, msg
    return msg


def test_the_untouched_archive_loads_with_its_settings(traced):
    """The base of every crafted archive below is accepted, settings read from its code's constants."""
    eager = eager_from_archive(traced)
    assert [type(m).__name__ for m in eager] == ["Linear", "Softmax", "LeakyReLU", "Softplus", "ReLU", "Identity"]
    assert eager[1].dim == 1 and eager[2].negative_slope == 0.2
    assert (eager[3].beta, eager[3].threshold) == (2.0, 10.0)


SOFTMAX = "torch.softmax(argument_1, 1)"
LEAKY = "torch.leaky_relu(argument_1, 0.20000000000000001)"
SOFTPLUS = "torch.softplus(argument_1, 2., 10.)"
RELU = "torch.relu(argument_1)"


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
    (lambda: nn.Sequential(_with(nn.Linear(3, 2), n=torch.zeros(1, dtype=torch.long))), "trace",
     "a non-float tensor (torch.int64); decoders hold floating-point weights only"),
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


def test_constants_and_several_trees_are_refused(traced, tmp_path):
    import pickle

    _refused(_with_entries(traced, tmp_path / "c.pt", {"constants.pkl": pickle.dumps((1.0,), protocol=2)}),
             "tensor constants used by its code (a decoder has none)")
    assert len(eager_from_archive(_with_entries(traced, tmp_path / "e.pt", {"constants.pkl": pickle.dumps(())}))) == 6
    with zipfile.ZipFile(traced) as z:
        pkl = next(z.read(n) for n in z.namelist() if n.endswith("/data.pkl"))
    path = _with_entries(traced, tmp_path / "two.pt", {})
    with zipfile.ZipFile(path, "a") as z:
        z.writestr("other/data.pkl", pkl)
    _refused(path, "several module trees")


def test_code_size_bound_is_on_all_code_files_together(traced, tmp_path, monkeypatch):
    import controlgs_adapter.formats.torchscript as ts

    with zipfile.ZipFile(traced) as z:
        sizes = [i.file_size for i in z.infolist() if "/code/" in i.filename and i.filename.endswith(".py")]
    assert len(sizes) >= 3
    monkeypatch.setattr(ts, "_MAX_CODE_BYTES", sum(sizes))
    assert len(eager_from_archive(traced)) == 6  # exactly at the bound: accepted
    monkeypatch.setattr(ts, "_MAX_CODE_BYTES", sum(sizes) - 1)  # each file fits, their total does not
    _refused(traced, f"over {sum(sizes) - 1} bytes of code")


# --------------------------------------------------------------------------------------------------
# cli.REQUIRES: a missing optional package stops the command before its work starts
# --------------------------------------------------------------------------------------------------

_DEMO_HINT = "which is not installed: pip install 'controlgs-adapter[demo]'"


@pytest.mark.parametrize("argv,blocked,purpose,missing", [
    (["demo"], "skimage", "controlgs demo (the built-in scene and the report's plots)", "scikit-image"),
    (["optics", "bench"], "skimage", "controlgs optics bench (the optics benchmark's test image and plot)",
     "scikit-image"),
    (["scene", "export"], "skimage", "controlgs scene export (exporting the built-in scene's views as PNG)",
     "scikit-image"),
    (["eval", "--run", "RUN"], "matplotlib", "controlgs eval (the report's plots)", "matplotlib"),
    (["demo"], "matplotlib", "controlgs demo (the built-in scene and the report's plots)", "matplotlib"),
])
def test_cli_refuses_a_missing_extra_before_any_work(tmp_path, monkeypatch, capsys, argv, blocked, purpose, missing):
    from controlgs_adapter.cli import main

    monkeypatch.setitem(sys.modules, blocked, None)  # ``import <blocked>`` raises ImportError
    out = tmp_path / "out"
    argv = [str(tmp_path / "run") if a == "RUN" else a for a in argv] + ["--out", str(out)]
    assert main(argv) == 2
    err = capsys.readouterr().err.strip()
    assert err == f"controlgs {argv[0]}: error: {purpose} needs {missing}, {_DEMO_HINT}", err
    assert not out.exists()


def test_cli_eval_needs_matplotlib_only(tmp_path, monkeypatch, capsys):
    """eval's table entry names matplotlib alone: without scikit-image it goes on (to its own error)."""
    from controlgs_adapter.cli import main

    monkeypatch.setitem(sys.modules, "skimage", None)
    assert main(["eval", "--run", str(tmp_path / "no-run"), "--out", str(tmp_path / "out")]) == 2
    err = capsys.readouterr().err
    assert err.startswith("controlgs eval: error: ") and "scikit-image" not in err and "no-run" in err, err


# --------------------------------------------------------------------------------------------------
# viewer.session: constructor refusals, heat_overlay, the LRU cache
# --------------------------------------------------------------------------------------------------

def test_viewer_session_refuses_baseline_names_and_no_views():
    from controlgs_adapter.errors import InputValueError
    from controlgs_adapter.viewer.session import ViewerSession

    with pytest.raises(InputValueError, match=r"adapter names \['ss'\] clash with the baselines \('no_ss', 'ss'\)"):
        ViewerSession(None, [object()], {"controlgs": "a.safetensors", "ss": "b.safetensors"})
    with pytest.raises(InputValueError, match=r"adapter names \['no_ss'\] clash"):
        ViewerSession(None, [object()], {"no_ss": "a.safetensors"})
    with pytest.raises(InputValueError, match="the viewer needs at least one view"):
        ViewerSession(None, [], {})


def test_viewer_cache_evicts_the_least_recently_used():
    from controlgs_adapter.viewer.session import _Cache

    made: list[str] = []
    cache = _Cache(2)

    def get(key: str) -> str:
        return cache.get_or(key, lambda: made.append(key) or key.upper())

    assert [get("a"), get("b"), get("a")] == ["A", "B", "A"] and made == ["a", "b"]  # a hit makes nothing
    get("c")  # over the size: b (used least recently) goes, a (just used) stays
    assert list(cache) == ["a", "c"] and made == ["a", "b", "c"]
    get("b")
    assert list(cache) == ["c", "b"] and made == ["a", "b", "c", "b"]


def _heat_by_hand(pixels: list[tuple[int, int, float]], w: int, h: int) -> torch.Tensor:
    """heat_overlay's documented map in float64 loops: per pixel the mean strength of the anchors in
    the k x k window (k = 2 max(1, round(max(h, w) / 48)) + 1, clipped at the borders), coloured on the
    4-stop heat map; alpha 0.55 min(1, 4 k^2 (anchors in the window) / (window pixels in the image))."""
    heat = [[0.0, 0.0, 0.2], [0.45, 0.05, 0.55], [0.9, 0.35, 0.1], [1.0, 0.95, 0.3]]
    r = max(1, round(max(h, w) / 48))
    k = 2 * r + 1
    out = torch.zeros(4, h, w, dtype=torch.float64)
    for y in range(h):
        for x in range(w):
            inside = [(u, v) for v in range(y - r, y + r + 1) for u in range(x - r, x + r + 1) if 0 <= u < w and 0 <= v < h]
            hits = [s for (u, v, s) in pixels if (u, v) in inside]
            lam = min(max(sum(hits) / len(hits), 0.0), 1.0) if hits else 0.0
            t = lam * 3
            i = min(math.floor(t), 2)
            for c in range(3):
                out[c, y, x] = heat[i][c] + (t - i) * (heat[i + 1][c] - heat[i][c])
            out[3, y, x] = 0.55 * min(1.0, k * k * 4.0 * len(hits) / len(inside))
    return out


@pytest.mark.parametrize("w,h", [(20, 12), (100, 30)])  # k = 3 and k = 5
def test_heat_overlay_against_loops(w, h):
    from controlgs_adapter.state import Camera
    from controlgs_adapter.viewer.session import heat_overlay

    f, cx, cy = 10.0, w / 2, h / 2
    cam = Camera(torch.eye(4), torch.tensor([[f, 0.0, cx], [0.0, f, cy], [0.0, 0.0, 1.0]]), w, h)
    landing = [(0, 0, 0.2), (3, 2, 0.9), (3, 2, 0.5), (w - 1, h - 1, 1.0), (w // 2, h // 2, 0.35), (7, 5, 1.7)]
    pts = [[(u + 0.5 - cx) / f * z, (v + 0.5 - cy) / f * z, z] for (u, v, _), z in zip(landing, (1.0, 2.0, 1.0, 3.0, 1.0, 1.0))]
    strength = [s for (_, _, s) in landing]
    # dropped: behind the camera, left of / below the image, a NaN strength
    pts += [[0.0, 0.0, -1.0], [(-0.5 - cx) / f, 0.0, 1.0], [0.0, (h + 0.5 - cy) / f, 1.0], [(5.5 - cx) / f, (5.5 - cy) / f, 1.0]]
    strength += [1.0, 1.0, 1.0, float("nan")]
    got = heat_overlay(torch.tensor(pts, dtype=torch.float64), torch.tensor(strength), cam)
    assert got.shape == (4, h, w)
    torch.testing.assert_close(got.double(), _heat_by_hand(landing, w, h), atol=1e-5, rtol=0)


# --------------------------------------------------------------------------------------------------
# commands.common.make_renderer: --renderer / --rasterizer
# --------------------------------------------------------------------------------------------------

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


def test_make_renderer_wraps_the_chosen_rasterizer(tmp_path):
    from argparse import Namespace

    from controlgs_adapter.backends.models.reference_model import NeuralGaussianModel
    from controlgs_adapter.commands.common import RasterizerRenderer, make_renderer
    from controlgs_adapter.errors import InputValueError
    from controlgs_adapter.rendering.protocol import renderer_for

    model = NeuralGaussianModel(6, feat_dim=8, n_offsets=2)
    assert make_renderer(Namespace(rasterizer=None, renderer=None), model) is None  # the model's own
    assert make_renderer(Namespace(rasterizer="auto", renderer=None), model) is None
    plain = make_renderer(Namespace(rasterizer="torch", renderer=None), model)
    assert isinstance(plain, RasterizerRenderer) and plain.rasterizer == "torch"
    assert type(plain.renderer) is type(renderer_for(model))

    (tmp_path / "rec.py").write_text(_RENDERER_FILE)
    wrapped = make_renderer(Namespace(rasterizer="torch", renderer=f"{tmp_path / 'rec.py'}:recorder"), model)
    assert isinstance(wrapped, RasterizerRenderer) and wrapped.rasterizer == "torch"
    assert wrapped.visible(model, None) == "VIS" and wrapped.render(model, None, "VIS", None) == "IMG"
    # the user's object itself is wrapped; the rasterizer is chosen around render only, for that call
    assert wrapped.renderer.seen == [("visible", None), ("render", "torch", "VIS")]
    from controlgs_adapter.rendering.rasterizers import _CHOICE
    assert _CHOICE.get() is None

    with pytest.raises(InputValueError, match=r"--rasterizer 'nope' is not registered; available: .*torch.*, auto"):
        make_renderer(Namespace(rasterizer="nope", renderer=None), model)
    with pytest.raises(InputValueError) as info:
        make_renderer(Namespace(rasterizer="gsplat", renderer=None), model)
    msg = str(info.value)
    assert msg.startswith("--rasterizer gsplat cannot render on cpu: ") and "pip install 'controlgs-adapter[gsplat]'" in msg


# --------------------------------------------------------------------------------------------------
# eager_from_script: refusals and settings read from a live TorchScript module
# --------------------------------------------------------------------------------------------------

class Linear(nn.Module):
    """Named like torch's Linear (so ``original_name`` says Linear), but its forward doubles the output."""

    def __init__(self) -> None:
        super().__init__()
        self.weight = nn.Parameter(torch.randn(2, 3))
        self.bias = nn.Parameter(torch.randn(2))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return 2.0 * torch.nn.functional.linear(x, self.weight, self.bias)


class LeakyReLU(nn.Module):
    """Named like torch's LeakyReLU, with no slope anywhere."""

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return torch.relu(x)


def _trace(module: nn.Module) -> torch.jit.ScriptModule:
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return torch.jit.trace(module, torch.randn(2, 3))


def test_eager_from_script_refusals():
    from controlgs_adapter.errors import TargetError
    from controlgs_adapter.formats.torchscript import eager_from_script

    with pytest.raises(TargetError, match=r"decoder 'mlp_x': the TorchScript module holds no Linear layer"):
        eager_from_script(torch.jit.script(nn.Sequential(nn.ReLU())), "mlp_x")
    with pytest.raises(TargetError, match=r"decoder 'mlp_x.1': TorchScript layer of type 'GELU' cannot be rebuilt .*"
                                          r"\(supported: Sequential of Identity, LeakyReLU, Linear, ReLU, SiLU, Sigmoid, "
                                          r"Softmax, Softplus, Tanh\)"):
        eager_from_script(torch.jit.script(nn.Sequential(nn.Linear(3, 2), nn.GELU())), "mlp_x")
    with pytest.raises(TargetError, match=r"decoder 'mlp_x': the TorchScript module does not take a \[rows, 3\] input"):
        eager_from_script(torch.jit.script(nn.Sequential(nn.Linear(3, 2), nn.Linear(4, 1))), "mlp_x")
    with pytest.raises(TargetError, match=r"decoder 'mlp_x': the eager rebuild .* does not reproduce its output"):
        eager_from_script(_trace(nn.Sequential(Linear())), "mlp_x")
    with pytest.raises(TargetError, match=r"mlp_x.1: cannot read LeakyReLU.negative_slope from its TorchScript code"):
        eager_from_script(_trace(nn.Sequential(nn.Linear(3, 2), LeakyReLU())), "mlp_x")


@pytest.mark.parametrize("convert", ["trace", "script"])
def test_eager_from_script_reads_each_setting(convert):
    """Settings from the traced code's constants (trace) or the module's attributes (script), each a
    different number so a swapped index or attribute shows; mode as stored."""
    from controlgs_adapter.formats.torchscript import eager_from_script

    module = nn.Sequential(nn.Linear(3, 3), nn.LeakyReLU(0.3), nn.Softplus(beta=1.5, threshold=7.0), nn.Softmax(dim=0))
    module.eval()
    sm = _trace(module) if convert == "trace" else torch.jit.script(module)
    eager = eager_from_script(sm)
    assert eager[1].negative_slope == 0.3 and (eager[2].beta, eager[2].threshold) == (1.5, 7.0) and eager[3].dim == 0
    assert not eager.training and not eager[1].training


# --------------------------------------------------------------------------------------------------
# the restricted unpickler and the module tree: hand-written data.pkl opcodes (protocol 2)
# --------------------------------------------------------------------------------------------------

_M = b"c__torch__.torch.nn.modules.container\nSequential\n"  # GLOBAL of the root's class


@pytest.mark.parametrize("pkl,what", [
    (_M + b"K\x01\x85\x81.", "object of class __torch__.torch.nn.modules.container.Sequential built with arguments"),
    (b"K\x01.", " is a pickled int, not a TorchScript module"),
    (_M + b")\x81K\x01b.", "module  (__torch__.torch.nn.modules.container.Sequential) whose state is not a plain dict"),
    (_M + b")\x81}K\x01K\x02sb.", "whose state is not a plain dict"),  # a non-string key
    (_M + b")\x81}X\x01\x00\x00\x00xK\x01\x85sb.", "attribute .x holding a tuple"),
    (b"K\x01Q.", "an unexpected persistent id '1'"),
    (b"(X\x07\x00\x00\x00storagectorch\nLongStorage\nX\x01\x00\x00\x000X\x03\x00\x00\x00cpuK\x01tQ.",
     "a non-float tensor (torch.int64)"),
    (b"(X\x07\x00\x00\x00storagectorch\nFloatStorage\nX\x01\x00\x00\x00aX\x03\x00\x00\x00cpuK\x01tQ.",
     "an unexpected persistent id"),  # a storage key that is not a number
    (b"cbuiltins\neval\n.", "a pickled reference to the global 'builtins.eval'"),
    (b"c__torch__.a-b\nM\n.", "a pickled reference to the global '__torch__.a-b.M'"),  # not identifiers
])
def test_pickle_refusals(traced, tmp_path, pkl, what):
    _refused(_with_entries(traced, tmp_path / "p.pt", {"data.pkl": b"\x80\x02" + pkl}), what)


def _nested(tmp_path: Path, name: str, fill: float | None = None) -> tuple[Path, nn.Module]:
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


def test_tensors_from_archive_names_values_and_non_finite(tmp_path):
    from controlgs_adapter.formats.torchscript import tensors_from_archive

    path, module = _nested(tmp_path, "ok.pt")
    got = tensors_from_archive(path)
    want = module.state_dict()
    assert list(got) == list(want) == ["0.weight", "0.bias", "1.0.weight", "1.0.bias"]
    assert all(torch.equal(got[k], want[k]) for k in want)
    eager = eager_from_archive(path)  # requires_grad as stored, per tensor
    assert [p.requires_grad for p in eager.parameters()] == [False, True, True, True]
    for fill, word in ((float("inf"), "inf"), (float("-inf"), "inf"), (float("nan"), "NaN")):
        bad, _ = _nested(tmp_path, f"bad_{word}.pt", fill)
        for load in (tensors_from_archive, eager_from_archive):
            with pytest.raises(FileFormatError) as info:
                load(bad)
            assert str(bad) in str(info.value) and f"non-finite weights ({word}) in 1.0.bias" in str(info.value)


def _ints(values: tuple[int, ...]) -> bytes:
    return b"(" + b"".join(b"J" + v.to_bytes(4, "little", signed=True) for v in values) + b"t"


def _record(size: tuple[int, ...], stride: tuple[int, ...], offset: int = 0, requires_grad: bytes = b"\x89",
            hooks: bytes = b"", storage: bytes = b"FloatStorage", numel: int = 6) -> bytes:
    """Opcodes of ``torch._utils._rebuild_tensor_v2(storage data/0, offset, size, stride, requires_grad, hooks)``."""
    pid = (b"(X\x07\x00\x00\x00storagectorch\n" + storage + b"\nX\x01\x00\x00\x000X\x03\x00\x00\x00cpu"
           + b"J" + numel.to_bytes(4, "little") + b"tQ")
    return (b"ctorch._utils\n_rebuild_tensor_v2\n(" + pid + b"J" + offset.to_bytes(4, "little", signed=True)
            + _ints(size) + _ints(stride) + requires_grad + b"ccollections\nOrderedDict\n)R" + hooks + b"tR")


@pytest.mark.parametrize("pkl,what", [
    # the base archive's data/0 holds 6 float32 (its Linear's weight); every record below points at it
    (_record((1,) * 8, (1,) * 8), "is a pickled _TensorRecord, not a TorchScript module"),  # 8 dims: read
    (_record((1,) * 9, (1,) * 9), "a malformed tensor record"),  # over _MAX_DIMS
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


@pytest.mark.parametrize("channels,mode", [(3, "RGB"), (4, "RGBA")])
def test_encode_png_rounds_to_nearest_and_clamps(channels, mode):
    import base64
    import io

    from PIL import Image

    from controlgs_adapter.viewer.session import encode_png

    # x * 255: 127.5 -> 128, 127.49 -> 127, 0.51 -> 1, 0.49 -> 0, 254.6 -> 255; out of [0, 1] clamps
    values = torch.tensor([127.5, 127.49, 0.51, 0.49, 254.6, -20.0, 300.0, 255.0]) / 255.0
    image = values.view(1, 2, 4).expand(channels, 2, 4).clone()
    image[0, 0, 0] = 1.0  # channels differ: the channel order shows
    png = Image.open(io.BytesIO(base64.b64decode(encode_png(image))))
    assert png.mode == mode and png.size == (4, 2)
    got = torch.tensor(list(png.getdata())).T.reshape(channels, 2, 4)
    want = torch.tensor([128, 127, 1, 0, 255, 0, 255, 255]).view(1, 2, 4).expand(channels, 2, 4).clone()
    want[0, 0, 0] = 255
    assert torch.equal(got, want)


def test_cli_import_errors_outside_the_table_are_one_line(tmp_path, monkeypatch, capsys):
    """A package missing at the command's own import (not in REQUIRES) and a broken install (a name
    missing from a module) each end in one line and exit code 2, never a traceback."""
    import controlgs_adapter.report as report
    from controlgs_adapter.cli import main

    pytest.importorskip("matplotlib")
    argv = ["eval", "--run", str(tmp_path / "run"), "--out", str(tmp_path / "out")]
    with monkeypatch.context() as mp:
        mp.setitem(sys.modules, "controlgs_adapter.report", None)
        assert main(argv) == 2
    err = capsys.readouterr().err
    assert err == ("controlgs eval: error: needs the Python package 'controlgs_adapter.report', which is not installed "
                   "(pip install 'controlgs-adapter[demo]' installs the optional ones)\n"), err
    monkeypatch.delattr(report, "write_report")
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert err.startswith("controlgs eval: error: cannot import name 'write_report' from 'controlgs_adapter.report'"), err
    assert err.endswith(" (pip install 'controlgs-adapter[demo]' installs the optional ones)\n") and err.count("\n") == 1


@pytest.mark.parametrize("dim", [b"K\x00", b"K\x01"])
def test_a_stored_softmax_dim_is_an_unexpected_attribute(traced, tmp_path, dim):
    """torch.jit keeps Softmax's dim in the code only (a Final constant); a dim in the pickled state,
    equal to the code's (1) or not, is refused like any attribute a decoder does not hold."""
    import re

    with zipfile.ZipFile(traced) as z:
        pkl = next(z.read(n) for n in z.namelist() if n.endswith("/data.pkl"))
    crafted, n = re.subn(rb"(activation\nSoftmax\nq.\)\x81\}\()", lambda m: m.group(1) + b"X\x03\x00\x00\x00dim" + dim, pkl)
    assert n == 1
    _refused(_with_entries(traced, tmp_path / "d.pt", {"data.pkl": crafted}), "1 (Softmax) with unexpected attributes ['dim']")


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


def _looking(centre: tuple[float, ...], forward: tuple[float, ...]):
    """An OpenCV camera at ``centre`` looking along the horizontal unit ``forward`` (y down)."""
    from controlgs_adapter.state import Camera

    f = torch.tensor(forward, dtype=torch.float64)
    d = torch.tensor([0.0, -1.0, 0.0], dtype=torch.float64)
    r = torch.linalg.cross(d, f)
    w2c = torch.eye(4, dtype=torch.float64)
    w2c[:3, :3] = torch.stack([r, d, f])
    w2c[:3, 3] = -(w2c[:3, :3] @ torch.tensor(centre, dtype=torch.float64))
    return Camera(w2c, torch.tensor([[10.0, 0.0, 8.0], [0.0, 10.0, 8.0], [0.0, 0.0, 1.0]], dtype=torch.float64), 16, 16)


def test_scene_centre_each_branch():
    """Axes meeting in front: their meeting point; meeting behind, parallel or one camera: the anchors'
    per-axis median; no anchors either: the origin."""
    from controlgs_adapter.viewer.session import scene_centre

    t = (0.5, -1.0, 2.0)
    front = [_looking((t[0] - 3, t[1], t[2]), (1.0, 0.0, 0.0)), _looking((t[0], t[1], t[2] - 3), (0.0, 0.0, 1.0))]
    behind = [_looking((t[0] - 3, t[1], t[2]), (-1.0, 0.0, 0.0)), _looking((t[0], t[1], t[2] - 3), (0.0, 0.0, -1.0))]
    parallel = [_looking((0.0, 0.0, 0.0), (0.0, 0.0, 1.0)), _looking((1.0, 0.0, 0.0), (0.0, 0.0, 1.0))]
    points = torch.tensor([[0.0, 0.0, 0.0], [1.0, 1.0, 1.0], [5.0, -2.0, 3.0]])
    median = torch.tensor([1.0, 0.0, 1.0], dtype=torch.float64)
    torch.testing.assert_close(scene_centre(front, points), torch.tensor(t, dtype=torch.float64), atol=1e-12, rtol=0)
    for cams in (behind, parallel, front[:1]):
        torch.testing.assert_close(scene_centre(cams, points), median, atol=0, rtol=0)
        assert torch.equal(scene_centre(cams, None), torch.zeros(3, dtype=torch.float64))
        assert torch.equal(scene_centre(cams, torch.zeros(0, 3)), torch.zeros(3, dtype=torch.float64))


def test_settings_with_signs_and_exponents(tmp_path):
    """Negative and exponent-written constants in traced code read exactly, live and from the file."""
    from controlgs_adapter.formats.torchscript import eager_from_script

    module = nn.Sequential(nn.Linear(3, 3), nn.LeakyReLU(-0.5), nn.Softplus(beta=2.5e-7, threshold=1e20), nn.Softmax(dim=-1))
    sm = _trace(module)
    path = tmp_path / "s.pt"
    torch.jit.save(sm, str(path))
    for eager in (eager_from_script(sm), eager_from_archive(path)):
        assert eager[1].negative_slope == -0.5 and (eager[2].beta, eager[2].threshold) == (2.5e-7, 1e20)
        assert eager[3].dim == -1


_CHAIN = "(_4).forward((_3).forward((_2).forward(_6, ), ), )"


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


def test_entry_count_and_pickle_size_bounds(traced, tmp_path, monkeypatch):
    """Each bound accepts an archive exactly at it and refuses one a unit over."""
    import controlgs_adapter.formats.torchscript as ts

    with zipfile.ZipFile(traced) as z:
        count = len(z.infolist())
        pkl = next(i for i in z.infolist() if i.filename.endswith("/data.pkl"))
    monkeypatch.setattr(ts, "_MAX_ENTRIES", count)
    assert len(eager_from_archive(traced)) == 6
    monkeypatch.setattr(ts, "_MAX_ENTRIES", count - 1)
    _refused(traced, f"{count} zip entries (at most {count - 1}; not a decoder archive)")
    monkeypatch.setattr(ts, "_MAX_ENTRIES", count)
    monkeypatch.setattr(ts, "_MAX_PICKLE_BYTES", pkl.file_size)
    assert len(eager_from_archive(traced)) == 6
    monkeypatch.setattr(ts, "_MAX_PICKLE_BYTES", pkl.file_size - 1)
    _refused(traced, f"entry '{pkl.filename}' of {pkl.file_size} bytes (at most {pkl.file_size - 1})")


@pytest.mark.parametrize("levels,ok", [(32, True), (33, False)])
def test_nesting_bound(tmp_path, levels, ok):
    """A Linear under 32 nested Sequentials (depth 32) is read; one level more is refused, naming where."""
    module: nn.Module = nn.Linear(3, 2)
    for _ in range(levels):
        module = nn.Sequential(module)
    path = tmp_path / "n.pt"
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        torch.jit.save(torch.jit.trace(module, torch.randn(2, 3)), str(path))
    if ok:
        got = eager_from_archive(path)
        for _ in range(levels):
            got = got[0]
        assert torch.equal(got.weight, module.get_submodule(".".join(["0"] * levels)).weight)
    else:
        _refused(path, "modules nested deeper than 32 (or a cycle) at " + ".".join(["0"] * 33))
