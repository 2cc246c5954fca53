"""The public API: every name ``controlgs_adapter`` and its subpackages export (their ``__all__``) with
its call signature, compared with the committed snapshot ``public_api.txt`` next to this file, so an
API change is a visible decision; and the package's names that load on first use."""

from __future__ import annotations

import dataclasses
import difflib
import functools
import importlib
import inspect
import os
import pkgutil
import re
import subprocess
import sys
from pathlib import Path
from typing import Any

import pytest

import controlgs_adapter
from controlgs_adapter.losses import LossWeights
from controlgs_adapter.state import RuntimeState
from controlgs_adapter.training import TrainConfig, Trainer

SNAPSHOT = Path(__file__).with_name("public_api.txt")
UPDATE = "CONTROLGS_UPDATE_API_SNAPSHOT"
PACKAGE = "controlgs_adapter"


def _ours(obj: Any) -> bool:
    return (getattr(obj, "__module__", None) or "").split(".")[0] == PACKAGE


def _signature(obj: Any) -> str:
    """``inspect.signature`` as text, object addresses in default values left out."""
    try:
        return re.sub(r" at 0x[0-9a-f]+", "", str(inspect.signature(obj)))
    except (TypeError, ValueError):
        return "(...)"


def _constructor(cls: type) -> str:
    """The class's call signature where this package defines its ``__init__`` (or ``__new__``), a
    dataclass's included, else '' (a constructor from torch, typing or the standard library is theirs)."""
    for klass in cls.__mro__:
        method = vars(klass).get("__init__", vars(klass).get("__new__"))
        if method is not None:
            qualname = getattr(getattr(method, "__func__", method), "__qualname__", "")
            return _signature(cls) if _ours(klass) and qualname.startswith(f"{klass.__qualname__}.") else ""
    return ""


def _members(cls: type) -> list[str]:
    """The public attributes the class itself defines: methods with their signatures, properties, and
    class attributes with their type (a dataclass's fields are in its constructor)."""
    fields = {f.name for f in dataclasses.fields(cls)} if dataclasses.is_dataclass(cls) else set()
    out = []
    for name, raw in sorted(vars(cls).items()):
        if name.startswith("_") or name in fields:
            continue
        if isinstance(raw, (property, functools.cached_property)):
            out.append(f"    .{name}: property")
        elif isinstance(raw, (staticmethod, classmethod)) or inspect.isfunction(raw):
            kind = {staticmethod: "staticmethod ", classmethod: "classmethod "}.get(type(raw), "")
            out.append(f"    {kind}.{name}{_signature(getattr(cls, name))}")
        elif inspect.isclass(raw):
            out.append(f"    .{name}: class")
        else:
            out.append(f"    .{name}: {type(raw).__name__}")
    return out


def describe(name: str, obj: Any) -> list[str]:
    """One exported name as text: a module, a class (constructor and members), a function with its
    signature, or a value with its type."""
    if inspect.ismodule(obj):
        return [f"{name}: module"]
    if inspect.isclass(obj):
        bases = ", ".join(b.__qualname__ for b in obj.__bases__ if b is not object)
        constructor = _constructor(obj)
        return [f"class {name}" + (f"({bases})" if bases else ""), *([f"    {name}{constructor}"] if constructor else []),
                *_members(obj)]
    if inspect.isfunction(obj) or (callable(obj) and hasattr(obj, "__wrapped__")):
        return [f"def {name}{_signature(obj)}"]
    return [f"{name}: {type(obj).__name__}"]


def public_packages() -> list[str]:
    """``controlgs_adapter`` and each of its subpackages that declares ``__all__``."""
    names = [PACKAGE]
    for info in sorted(pkgutil.iter_modules(controlgs_adapter.__path__), key=lambda i: i.name):
        if info.ispkg and hasattr(importlib.import_module(f"{PACKAGE}.{info.name}"), "__all__"):
            names.append(f"{PACKAGE}.{info.name}")
    return names


def api_text() -> str:
    lines = []
    for package in public_packages():
        module = importlib.import_module(package)
        lines.append(f"[{package}]")
        for name in sorted(module.__all__):
            lines += describe(name, getattr(module, name))
        lines.append("")
    return "\n".join(lines)


def test_public_api_matches_the_snapshot() -> None:
    """A changed, added or removed public name or signature fails here until the snapshot is regenerated."""
    current = api_text()
    if os.environ.get(UPDATE) == "1":
        SNAPSHOT.write_text(current)
    committed = SNAPSHOT.read_text() if SNAPSHOT.is_file() else ""
    if current != committed:
        diff = "".join(difflib.unified_diff(committed.splitlines(True), current.splitlines(True),
                                            f"{SNAPSHOT.name} (committed)", "the package now"))
        here = Path(__file__).relative_to(Path(__file__).parents[2])
        pytest.fail(f"the public API changed:\n{diff}\nIf the change is intended, regenerate the snapshot and commit it: "
                    f"{UPDATE}=1 .venv/bin/python -m pytest {here}", pytrace=False)


def test_public_api_text_shows_signatures_members_and_values() -> None:
    from controlgs_adapter import ControlGS, RuntimeState

    assert describe("RuntimeState", RuntimeState)[1].startswith("    RuntimeState(downsample: 'float' = 1.0")
    assert describe("ShapeError", controlgs_adapter.ShapeError) == ["class ShapeError(ControlGSError, ValueError)"]
    wrap = next(line for line in describe("ControlGS", ControlGS) if ".wrap(" in line)
    assert wrap.startswith("    classmethod .wrap(model") and "cond_dim: 'int' = 8" in wrap
    assert describe("errors", controlgs_adapter.errors) == ["errors: module"]
    assert describe("__version__", controlgs_adapter.__version__) == ["__version__: str"]
    assert "0x" not in api_text()  # no object addresses: the text is the same in every process


def test_names_load_on_first_use() -> None:
    """``import controlgs_adapter`` loads none of the lazily exported modules; naming one loads it."""
    code = ("import sys, controlgs_adapter as c; assert 'controlgs_adapter.training' not in sys.modules; "
            "assert 'controlgs_adapter.controlgs' not in sys.modules; "
            "c.TrainConfig; assert 'controlgs_adapter.training' in sys.modules")
    subprocess.run([sys.executable, "-c", code], check=True)


def test_every_public_name_resolves() -> None:
    import controlgs_adapter
    from controlgs_adapter.evaluation import GridResult

    for name in controlgs_adapter.__all__:
        assert getattr(controlgs_adapter, name) is not None, name
    assert controlgs_adapter.Trainer is Trainer and controlgs_adapter.GridResult is GridResult
    assert issubclass(controlgs_adapter.StateRangeError, controlgs_adapter.StateError)


def test_value_objects_are_frozen():
    from controlgs_adapter.controlgs import Target
    from controlgs_adapter.plugins import PluginInfo

    objs = [(LossWeights(), "l1"), (RuntimeState(), "downsample"), (TrainConfig(), "lr"),
            (Target("d", "d.0", 3, 4, False), "fc1"), (PluginInfo("stage", "n", "p", "s", None), "name")]
    for obj, field in objs:
        with pytest.raises(dataclasses.FrozenInstanceError):
            setattr(obj, field, 1)
    assert hash(LossWeights()) == hash(LossWeights(0.8, 0.2, 10.0, 0.0))  # frozen dataclasses hash by value
