"""What ``controlgs train`` and ``controlgs eval`` share for a user's own scene: the options naming a
trained model folder and its dataset, loading both, the up-front scene check and ``RUN/run.json``
(what a run was trained on, so that ``eval`` needs only ``--run``)."""

from __future__ import annotations

import argparse
import json
import os
import warnings
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any, Callable

from ..errors import ControlGSError, InputValueError

if TYPE_CHECKING:
    from ..downstream.optics.lenses import Lens

#: default working resolution of a user's dataset (longer side in pixels; never upscaled)
DEFAULT_DATA_RESOLUTION = 256
#: default budget of the decoded-image cache (MiB)
DEFAULT_CACHE_MIB = 1024
RUN_FILE = "run.json"
#: run.json keys that ``eval`` takes as defaults for its options
_RUN_DEFAULTS = ("model", "data", "family", "model_iteration", "format", "images", "holdout", "white_background",
                 "resolution", "allow_unquantized", "effects", "rasterizer", "renderer", "lens")


def add_data_arguments(p: argparse.ArgumentParser) -> None:
    """Options naming a user's model folder and dataset (``--model``/``--data`` and how to read them)."""
    from ..backends.model_dir import FAMILIES
    from ..datasets.detect import FORMATS

    g = p.add_argument_group("your own scene (without --model/--data: the built-in scene, --variant)")
    g.add_argument("--model", help="trained output folder of Scaffold-GS, Octree-GS, HAC++/HAC, ContextGS or CompGS "
                                   "(family detected from its files)")
    g.add_argument("--data", help="its dataset: COLMAP (sparse/0 + images/), Blender (transforms_{train,test}.json) or "
                                  "instant-ngp (transforms.json); format detected")
    g.add_argument("--family", choices=tuple(FAMILIES), default=None, help="the model folder's family (default: detected)")
    g.add_argument("--model-iteration", type=int, default=None, help="point_cloud/iteration_<N> to load (default: the last)")
    g.add_argument("--allow-unquantized", action="store_true", default=None,
                   help="HAC++/HAC/ContextGS raw checkpoints, CompGS: use the stored unquantised values (docs/reference/backends.md)")
    g.add_argument("--format", choices=FORMATS, default=None, help="dataset format (default: detected)")
    g.add_argument("--images", default=None, help="COLMAP image folder, e.g. images_4 (default: images/ or the "
                                                 "downscaled folder that fits --resolution)")
    g.add_argument("--holdout", type=int, default=None, help="every N-th view is a test view (COLMAP, instant-ngp; default 8)")
    g.add_argument("--white-background", action="store_true", default=None,
                   help="composite RGBA images over white (the model was trained with --white_background)")
    g.add_argument("--cache-mib", type=int, default=DEFAULT_CACHE_MIB,
                   help="memory budget of the decoded-image cache (MiB; images are read lazily, never all at once)")
    g.add_argument("--device", default="cpu", help="torch device of the model and the whole pipeline (cpu, cuda, cuda:1)")


def add_lens_argument(p: argparse.ArgumentParser, from_run: bool = False) -> None:
    """``--lens``: the headset lens the downstream path simulates (docs/how-to/own-lens.md)."""
    from ..downstream.optics.lenses import DEFAULT_LENS, SHIPPED_LENSES

    p.add_argument("--lens", default=None, metavar="LENS",
                   help=f"headset lens the downstream path simulates: a shipped lens ({', '.join(SHIPPED_LENSES)}), a PSF "
                        "bank .safetensors, a prescription or distortion-profile .json (default "
                        + ("the run's, else " if from_run else "") + f"{DEFAULT_LENS}; docs/how-to/own-lens.md)")


def load_lens_arg(args: argparse.Namespace) -> "Lens":
    """The :class:`~controlgs_adapter.downstream.optics.lenses.Lens` of ``--lens`` (unset: Cardboard)."""
    from ..downstream.optics.lenses import DEFAULT_LENS, check_lens_spec, load_lens

    spec = args.lens or DEFAULT_LENS
    check_lens_spec(spec, "--lens")
    return load_lens(spec)


def lens_record(lens: "Lens") -> str:
    """A lens for ``run.json``: a shipped lens by name, a file by its absolute path."""
    return lens.spec if lens.kind == "shipped" else str(Path(lens.spec).resolve())


def user_scene(args: argparse.Namespace) -> bool:
    """True when the command runs on a user's model + dataset (``--model``/``--data``), False for the
    built-in scene; half of the pair is an error."""
    if (args.model is None) != (args.data is None):
        raise InputValueError("give both --model MODEL_DIR and --data DATA_DIR (or neither, for the built-in scene)")
    return args.model is not None


#: largest ``run.json`` read (a real one is well under a kilobyte)
RUN_FILE_MAX_BYTES = 1 << 20


def _run_fields() -> dict[str, tuple[str, Callable[[Any], bool]]]:
    """``run.json`` field -> (what it must hold, test); every field may also be null."""
    from ..backends.model_dir import FAMILIES
    from ..datasets.detect import FORMATS
    from ..training import DEFAULT_EFFECTS

    def whole(low: int, high: int = 2**63 - 1) -> Callable[[Any], bool]:
        return lambda v: isinstance(v, int) and not isinstance(v, bool) and low <= v <= high

    def text(v: Any) -> bool:
        return isinstance(v, str) and bool(v) and "\0" not in v

    def words(v: Any) -> bool:
        return isinstance(v, list) and all(isinstance(x, str) for x in v)

    stages = (*DEFAULT_EFFECTS, "foveation")
    effects = ", ".join(stages)
    return {
        "model": ("a folder path (string)", text), "data": ("a folder path (string)", text),
        "images": ("a folder under the dataset (a relative path without '..')",
                   lambda v: text(v) and not Path(v).is_absolute() and ".." not in Path(v).parts),
        "renderer": ("MODULE:ATTR or path/to/file.py:ATTR (string)", text), "rasterizer": ("a rasterizer name", text),
        "family": (f"one of {', '.join(FAMILIES)}", lambda v: isinstance(v, str) and v in FAMILIES),
        "format": (f"one of {', '.join(FORMATS)}", lambda v: isinstance(v, str) and v in FORMATS),
        "variant": ("one of ar, vr", lambda v: isinstance(v, str) and v in ("ar", "vr")),
        "model_iteration": ("an integer >= 0", whole(0)), "holdout": ("an integer >= 0", whole(0)),
        "resolution": ("an integer >= 1", whole(1)), "iterations": ("an integer >= 0", whole(0)),
        "seed": ("an integer >= 0", whole(0)), "seeds": ("an integer >= 1", whole(1)),
        "allow_unquantized": ("true or false", lambda v: isinstance(v, bool)),
        "white_background": ("true or false", lambda v: isinstance(v, bool)),
        "effects": (f"a non-empty list of stage names among {effects}",
                    lambda v: words(v) and bool(v) and all(x in stages for x in v)),
        "adapters": ("a list of adapter names", words),
        "lens": ("a shipped lens name or a file path (string)", text),
        "distributed": ("an object (processes, backend, exchange)",
                        lambda v: isinstance(v, dict) and all(isinstance(x, (str, int, type(None))) for x in v.values())),
    }


def read_run(run_dir: Path) -> dict[str, Any] | None:
    """``run_dir/run.json`` (written by ``controlgs train``), every field it has checked; None when
    there is none. Refused in one line naming the file and the field: not JSON, not an object, a
    field of the wrong type or value. Reading it runs nothing."""
    path = Path(run_dir) / RUN_FILE
    if not path.exists():
        return None
    try:
        if not path.is_file():
            raise InputValueError(f"{path}: not a controlgs run file (not a file)")
        if path.stat().st_size > RUN_FILE_MAX_BYTES:
            raise InputValueError(f"{path}: not a controlgs run file (larger than {RUN_FILE_MAX_BYTES} bytes)")
        run = json.loads(path.read_text(encoding="utf-8"))
    except InputValueError:
        raise
    except (OSError, ValueError, RecursionError) as e:
        raise InputValueError(f"{path}: not a controlgs run file ({type(e).__name__}: {e})") from None
    if not isinstance(run, dict):
        raise InputValueError(f"{path}: not a controlgs run file (a JSON {type(run).__name__}, expected an object)")
    for key, (what, ok) in _run_fields().items():
        value = run.get(key)
        if value is not None and not ok(value):
            shown = repr(value) if len(repr(value)) <= 60 else repr(value)[:57] + "..."
            raise InputValueError(f"{path}: field {key!r} must be {what}, got {shown}")
    return run


def apply_run_defaults(args: argparse.Namespace, run_dir: Path) -> dict[str, Any] | None:
    """Fill the options left unset from ``run_dir/run.json`` (:func:`read_run`); returns it. The run's
    renderer (code) is taken only with ``--trust-run-renderer``; otherwise a run that names one is
    refused unless ``--renderer`` is given again."""
    from ..downstream.optics.lenses import check_lens_spec

    run = read_run(run_dir)
    if run is None:
        return None
    taken = [k for k in _RUN_DEFAULTS if k != "renderer" and getattr(args, k, None) is None and run.get(k) is not None]
    checks: dict[str, tuple[Callable[[str], None], str]] = {"rasterizer": (check_rasterizer_name, "--rasterizer NAME"),
                                                           "lens": (check_lens_spec, "--lens NAME|PATH")}
    for key in taken:  # the values that name something outside the file, before any is taken
        if key in checks:
            check, option = checks[key]
            try:
                check(run[key])
            except ControlGSError as e:
                raise InputValueError(f"{run_dir / RUN_FILE}: field {key!r}: {e} (give {option})") from None
    for key in taken:
        setattr(args, key, run[key])
    spec = run.get("renderer")
    if spec is not None and getattr(args, "renderer", None) is None:
        if not getattr(args, "trust_run_renderer", False):
            raise InputValueError(f"{run_dir / RUN_FILE}: the run was trained with --renderer {spec}; a run folder's "
                                  f"code is not run unless you say so: give --renderer {spec} again (or "
                                  "--trust-run-renderer to use the run's)")
        args.renderer = spec
    return run


@dataclass
class UserScene:
    """A user's model and dataset, loaded. ``model`` on ``device``; ``resolution`` = longer side (pixels)."""

    model: Any
    family: str
    data: Any
    resolution: int
    device: Any

    def record(self, args: argparse.Namespace, **extra: Any) -> dict[str, Any]:
        """JSON-able description of the run (``run.json``; the report's info)."""
        return {"model": str(Path(args.model).resolve()), "data": str(Path(args.data).resolve()), "family": self.family,
                "model_iteration": args.model_iteration, "allow_unquantized": bool(args.allow_unquantized),
                "format": self.data.format, "images": args.images, "holdout": args.holdout,
                "white_background": bool(args.white_background), "resolution": self.resolution, **extra}


def parse_device(name: str) -> Any:
    """``--device`` as a ``torch.device``, refused (one line) when unknown or when CUDA is missing."""
    import torch

    try:
        device = torch.device(name)
    except RuntimeError as e:
        raise InputValueError(f"--device {name!r}: {e}") from None
    if device.type == "cuda" and not torch.cuda.is_available():
        raise InputValueError(f"--device {name}: CUDA is not available on this machine")
    if device.type == "meta":
        raise InputValueError(f"--device {name}: a meta device holds no data; use cpu or cuda")
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            torch.zeros(1, device=device).cpu()
    except Exception as e:  # an unavailable index (cuda:3 on one GPU), a backend this torch lacks
        why = (str(e).strip().splitlines() or [type(e).__name__])[0][:160]
        raise InputValueError(f"--device {name}: cannot hold tensors on this machine ({why})") from None
    return device


#: CLI options checked up front by :func:`check_options`: dest -> check_number limits
_NUMBER_OPTIONS: dict[str, dict[str, Any]] = {
    "iterations": dict(integer=True, low=0), "seed": dict(integer=True, low=0, high=2**63 - 1),
    "seeds": dict(integer=True, low=1), "lr": dict(low=0.0, low_open=True, high=1e3),
    "psf_fraction": dict(low=0.0, high=1.0), "cond_dim": dict(integer=True, low=1),
    "checkpoint_every": dict(integer=True, low=0), "batch_size": dict(integer=True, low=1),
    "resolution": dict(integer=True, low=1),
    "test_views": dict(integer=True, low=1), "holdout": dict(integer=True, low=0),
    "model_iteration": dict(integer=True, low=0), "cache_mib": dict(integer=True, low=0),
}


def check_options(args: argparse.Namespace) -> None:
    """Check, before anything is loaded or written, every option of a command that it has: the numbers
    (one line naming ``--option`` and the value), ``--effects``, ``--device``, ``--rasterizer``."""
    from ..checks import check_number
    from ..downstream.optics.lenses import check_lens_spec
    from .adapters import effects_from

    for dest, limits in _NUMBER_OPTIONS.items():
        value = getattr(args, dest, None)
        if value is not None:
            if limits.get("integer"):  # counts and sizes fit an int64 (--iterations 10**400 is one line)
                limits = {"high": 2**63 - 1, **limits}
            check_number("--" + dest.replace("_", "-"), value, **limits)
    if getattr(args, "effects", None) is not None:
        effects_from(args.effects)
    if getattr(args, "device", None) is not None:
        parse_device(args.device)
    if hasattr(args, "rasterizer"):
        check_rasterizer_name(args.rasterizer)
    if getattr(args, "lens", None) is not None:
        check_lens_spec(args.lens, "--lens")


def check_out_path(path: Any, option: str, *, folder: bool) -> Path:
    """Refuse, before any work and creating nothing, an output path (``option``'s) that cannot be written:
    a file where a folder is written (``folder``) or a folder where a file is, a file in the way of
    its folder, a place this process may not write. Returns it as a :class:`Path`."""
    from ..errors import FileWriteError
    from ..formats.safetensors import as_path

    p = as_path(path, option)
    try:
        if folder and p.exists() and not p.is_dir():
            raise InputValueError(f"{option} {p}: is a file; expected a folder to write into")
        if not folder and p.is_dir():
            raise InputValueError(f"{option} {p}: is a folder; expected the path of a file to write")
        above = p if folder else p.parent
        while not above.exists() and above != above.parent:
            above = above.parent
        if not above.is_dir():
            raise InputValueError(f"{option} {p}: {above} is a file, not a folder")
        if not os.access(above, os.W_OK | os.X_OK):
            raise FileWriteError(f"{option} {p}: cannot write into {above} (permission denied)")
    except (OSError, ValueError) as e:
        if isinstance(e, (InputValueError, FileWriteError)):
            raise
        raise InputValueError(f"{option} {p}: not a usable path ({e})") from None
    return p


def load_user_scene(args: argparse.Namespace) -> UserScene:
    """Load ``--model`` (family detected unless ``--family``) onto ``--device`` and read ``--data``."""

    from ..backends.model_dir import detect_family, load_model_dir
    from ..datasets.detect import load_dataset

    device = parse_device(args.device)
    if args.resolution is None:
        args.resolution = DEFAULT_DATA_RESOLUTION
    if args.holdout is None:
        args.holdout = 8
    family = args.family or detect_family(args.model, iteration=args.model_iteration)
    model = load_model_dir(args.model, family=family, iteration=args.model_iteration,
                           allow_unquantized=bool(args.allow_unquantized)).to(device)
    data = load_dataset(args.data, format=args.format, images=args.images, resolution=args.resolution,
                        holdout=args.holdout, white_background=bool(args.white_background))
    return UserScene(model, family, data, int(args.resolution), device)


def anchor_positions(model: Any) -> Any:
    """``[A, 3]`` anchor positions of ``model`` as the backend that recognises it reads them (CPU)."""
    from .. import plugins

    for info in plugins.backends().values():
        if info.obj.matches(model):
            return info.obj.anchor_positions(model).detach().float().cpu()
    return None


def check_line(report: dict[str, Any]) -> str:
    """One line summing up :func:`~controlgs_adapter.datasets.check_scene`'s report."""
    splits = ", ".join(f"{n} {s}" for s, n in report["splits"].items())
    line = f"scene check: {report['format'] or 'dataset'} {report['source']}: {splits} views, image sizes match their cameras"
    seen = report["in_front"]
    if seen:
        ok = len(seen) - len(report["blind"])
        line += (f"; the model's {report['points']} anchors are in view of {ok}/{len(seen)} cameras "
                 f"(median {sorted(seen.values())[len(seen) // 2]:.0%} inside the image)")
    return line


def cache_bytes(args: argparse.Namespace) -> int:
    """``--cache-mib`` in bytes (checked: an int >= 0)."""
    mib = getattr(args, "cache_mib", DEFAULT_CACHE_MIB)
    if not isinstance(mib, int) or mib < 0:
        raise InputValueError(f"--cache-mib must be an int >= 0 (MiB), got {mib!r}")
    return mib << 20


def add_render_arguments(p: argparse.ArgumentParser, from_run: bool = False) -> None:
    """``--rasterizer`` and ``--renderer`` (docs/how-to/own-renderer.md); ``from_run``: also
    ``--trust-run-renderer`` (a command that reads a run folder)."""
    g = p.add_argument_group("rendering (docs/how-to/own-renderer.md; default: a train run's, from RUN/run.json)")
    g.add_argument("--rasterizer", default=None, metavar="NAME",
                   help="rasterizer of the renders: a registered one (torch, gsplat, plug-ins: `controlgs plugins`) or "
                        "auto (default: gsplat on CUDA where installed, else torch)")
    g.add_argument("--renderer", default=None, metavar="MODULE:ATTR",
                   help="your own renderer: a Renderer object (visible(model, camera), render(model, camera, visible, "
                        "background)) or a render function render(model, camera, visible, background), named as "
                        "MODULE:ATTR (importable, or from the current folder) or path/to/file.py:ATTR")
    if from_run:
        g.add_argument("--trust-run-renderer", action="store_true",
                       help="use the renderer RUN/run.json names (its code runs); without it a run trained with "
                            "--renderer needs --renderer again")


def check_rasterizer_name(name: str | None) -> None:
    """Refuse a ``--rasterizer`` that is not registered (one line listing those that are)."""
    from .. import plugins

    registered = list(plugins.rasterizers())
    if name is not None and name != "auto" and name not in registered:
        raise InputValueError(f"--rasterizer {name!r} is not registered; available: {', '.join(registered)}, auto")


def load_renderer(spec: str) -> Any:
    """The :class:`~controlgs_adapter.rendering.protocol.Renderer` of ``--renderer MODULE:ATTR`` (or
    ``FILE.py:ATTR``): an object with ``visible`` and ``render``, or a render function (all anchors
    decoded). Refused in one line: a malformed spec, a missing module, file or attribute, an object
    that does not fit the protocol (a class, not callable, methods that do not take its arguments)."""
    import importlib
    import importlib.util
    import inspect
    import sys

    from ..rendering.protocol import Renderer, as_renderer

    where, sep, attr = spec.rpartition(":")
    if not sep or not where or not attr.isidentifier():
        raise InputValueError(f"--renderer must be MODULE:ATTR or path/to/file.py:ATTR, got {spec!r}")
    if where.endswith(".py"):
        path = Path(where)
        if not path.is_file():
            raise InputValueError(f"--renderer {spec}: no such file {path}")
        loader = importlib.util.spec_from_file_location(f"controlgs_user_renderer_{path.stem}", path)
        if loader is None or loader.loader is None:
            raise InputValueError(f"--renderer {spec}: {path} is not a Python module")
        module = importlib.util.module_from_spec(loader)
        loader.loader.exec_module(module)
    else:
        sys.path.insert(0, str(Path.cwd()))  # a module of the current folder, as `python -m` would find it
        try:
            module = importlib.import_module(where)
        except ModuleNotFoundError as e:
            if e.name is None or not (where == e.name or where.startswith(e.name + ".")):
                raise  # a module the renderer's module imports
            raise InputValueError(f"--renderer {spec}: no module named {e.name!r} (on the Python path or in the current "
                                  f"folder; or give a file: path/to/file.py:{attr})") from None
        finally:
            sys.path.remove(str(Path.cwd()))
    if not hasattr(module, attr):
        raise InputValueError(f"--renderer {spec}: {where} has no attribute {attr!r}")
    obj = getattr(module, attr)
    fits = "a Renderer object (visible(model, camera), render(model, camera, visible, background)) or a render function render(model, camera, visible, background)"
    if isinstance(obj, type):
        raise InputValueError(f"--renderer {spec}: {attr} is a class; name an instance of it or a function: {fits}")
    methods = ((obj.visible, 2), (obj.render, 4)) if isinstance(obj, Renderer) else ((obj, 4),) if callable(obj) else ()
    try:
        if not methods or any(not callable(fn) for fn, _ in methods):
            raise TypeError(f"a {type(obj).__name__}")
        for fn, n in methods:
            inspect.signature(fn).bind(*([None] * n))
    except TypeError as e:
        raise InputValueError(f"--renderer {spec}: {attr} does not fit the render protocol ({e}); expected {fits}") from None
    except ValueError:  # no signature to inspect (a builtin): accepted, checked at the first render
        pass
    return as_renderer(obj, None)


class RasterizerRenderer:
    """``renderer`` with its renders rasterized by ``rasterizer`` (set for each call, so it holds in
    any thread: the viewer renders in a worker)."""

    def __init__(self, renderer: Any, rasterizer: str) -> None:
        self.renderer, self.rasterizer = renderer, rasterizer

    def visible(self, model: Any, camera: Any) -> Any:
        return self.renderer.visible(model, camera)

    def render(self, model: Any, camera: Any, visible: Any, background: Any) -> Any:
        from ..rendering.rasterizers import use_rasterizer

        with use_rasterizer(self.rasterizer):
            return self.renderer.render(model, camera, visible, background)

    def __repr__(self) -> str:
        return f"{self.renderer!r} with rasterizer {self.rasterizer!r}"


def make_renderer(args: argparse.Namespace, model: Any) -> Any:
    """The renderer of ``--renderer`` / ``--rasterizer`` for ``model`` (None: neither given, the model's
    own). ``--rasterizer`` is checked against the model's device (one line: why it cannot run,
    and for gsplat the extra to install)."""
    import torch

    from .. import plugins
    from ..rendering.protocol import model_device, renderer_for

    check_rasterizer_name(args.rasterizer)
    renderer = load_renderer(args.renderer) if args.renderer else None
    if args.rasterizer in (None, "auto"):
        return renderer
    device = model_device(model)
    why = plugins.rasterizers()[args.rasterizer].obj.unavailable(device, torch.float32)
    if why is not None:
        hint = ("; it needs --device cuda and the gsplat extra: pip install 'controlgs-adapter[gsplat]' (or pip install "
                "--no-deps gsplat to keep your torch; docs/how-to/gpu.md)") if args.rasterizer == "gsplat" else ""
        raise InputValueError(f"--rasterizer {args.rasterizer} cannot render on {device}: {why}{hint}")
    return RasterizerRenderer(renderer if renderer is not None else renderer_for(model), args.rasterizer)


def render_record(args: argparse.Namespace) -> dict[str, Any]:
    """``--rasterizer`` / ``--renderer`` for ``run.json`` (a file renderer by its absolute path)."""
    spec = args.renderer
    if spec is not None and spec.rpartition(":")[0].endswith(".py"):
        where, _, attr = spec.rpartition(":")
        spec = f"{Path(where).resolve()}:{attr}"
    return {"rasterizer": args.rasterizer or "auto", "renderer": spec}
