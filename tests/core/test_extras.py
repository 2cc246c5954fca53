"""Optional dependencies: which packages each extra needs (a real, file-backed import), the one-line
error naming what to install, and every command that needs an extra checking it before any work."""

from __future__ import annotations

import re
import sys
import types
from typing import Any

import pytest

from controlgs_adapter import cli, extras
from controlgs_adapter.errors import MissingDependencyError


def _cli(argv: list[str], capsys: pytest.CaptureFixture[str]) -> str:
    """Run the CLI in-process: exit code 2, exactly one line on stderr, no traceback; returns it."""
    code = cli.main(argv)
    err = capsys.readouterr().err
    assert code == 2, (code, err)
    lines = err.strip().splitlines()
    assert len(lines) == 1 and "Traceback" not in err, err
    return lines[0]


class _StandIn(types.ModuleType):
    """What colour-science puts in place of a missing matplotlib: a module without a file."""

    def __getattr__(self, name: str) -> Any:
        raise AttributeError(name)


DEP_CASES = [
    ("demo without matplotlib", ["demo", "--out", "{d}/r"], "matplotlib"),
    ("eval without matplotlib", ["eval", "--run", "{d}/r"], "matplotlib"),
    ("eval --out without matplotlib", ["eval", "--run", "{d}/r", "--out", "{d}/r"], "matplotlib"),
    ("optics bench without matplotlib", ["optics", "bench", "--out", "{d}/r"], "matplotlib"),
    ("scene export without matplotlib", ["scene", "export", "--out", "{d}/r"], "matplotlib"),
    ("demo without scikit-image", ["demo", "--out", "{d}/r"], "scikit-image"),
]


@pytest.mark.parametrize("argv, missing", [c[1:] for c in DEP_CASES], ids=[c[0] for c in DEP_CASES])
def test_missing_optional_dependency_is_checked_first(tmp_path, capsys, monkeypatch, argv, missing):
    if missing == "matplotlib":
        monkeypatch.setitem(sys.modules, "matplotlib", _StandIn("matplotlib"))
    else:
        monkeypatch.setitem(sys.modules, "skimage", None)
    try:
        cli.build_parser().parse_args([a.replace("{d}", str(tmp_path)) for a in argv])
    except SystemExit:
        pytest.fail(f"{argv[0]} no longer parses {argv}: update the case")
    line = _cli([a.replace("{d}", str(tmp_path)) for a in argv], capsys)
    assert missing in line and "controlgs-adapter[demo]" in line, line
    assert not (tmp_path / "r").exists(), "the work must not have started"


def test_extras_usable_only_for_real_file_backed_packages(monkeypatch):
    assert extras.EXTRAS["optics"] == (("optiland", "optiland", ()),)
    assert [e[:2] for e in extras.EXTRAS["demo"]] == [("skimage", "scikit-image"), ("matplotlib", "matplotlib")]
    monkeypatch.setitem(sys.modules, "cgs_standin_pkg", types.ModuleType("cgs_standin_pkg"))  # no __file__
    monkeypatch.setitem(extras.EXTRAS, "t", (("json", "json-dist", ("json.decoder",)),
                                             ("cgs_standin_pkg", "standin-dist", ()),
                                             ("cgs_no_such_module_xyz", "absent-dist", ()),
                                             ("json", "json-broken", ("json.no_such_sub",))))
    assert extras.missing_modules("t") == ["standin-dist", "absent-dist", "json-broken"]
    assert extras.missing_modules("t", only=("cgs_standin_pkg",)) == ["standin-dist"]
    assert extras.missing_modules("t", only=("other",)) == []
    extras.require("t", "the thing", only=("other",))
    with pytest.raises(MissingDependencyError) as e:
        extras.require("t", "the thing", only=("cgs_standin_pkg", "cgs_no_such_module_xyz"))
    assert re.match(r"the thing needs standin-dist and absent-dist\b.*pip install 'controlgs-adapter\[t\]'$", str(e.value))
