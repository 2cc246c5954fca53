"""The command line prints a warning as one line ``controlgs <cmd>: warning: <message>`` (no file, line or
source), for the duration of the command only; library warnings point at the Python caller's line."""

from __future__ import annotations

import argparse
import subprocess
import sys
import warnings

import pytest

from controlgs_adapter import cli
from controlgs_adapter.commands import plugins as plugins_command
from controlgs_adapter.errors import warn_user


def _warning_command(monkeypatch, emit) -> None:
    """``controlgs plugins`` runs ``emit`` instead of listing the plug-ins."""
    def run(args: argparse.Namespace) -> int:
        emit()
        return 0

    monkeypatch.setattr(plugins_command, "run", run)


def _cli_in_a_fresh_process(emit: str) -> subprocess.CompletedProcess:
    """``controlgs plugins`` whose run is the Python statement ``emit``, in a fresh interpreter (as from
    a shell: no test harness recording the warnings)."""
    code = ("import sys, warnings\n"
            "from controlgs_adapter import cli\n"
            "from controlgs_adapter.commands import plugins\n"
            "from controlgs_adapter.errors import warn_user\n"
            f"plugins.run = lambda args: ({emit}, 0)[1]\n"
            "before = warnings.formatwarning\n"
            "code = cli.main(['plugins'])\n"
            "assert warnings.formatwarning is before\n"
            "sys.exit(code)\n")
    return subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300)


def test_a_warning_is_one_line_naming_the_command():
    done = _cli_in_a_fresh_process("warnings.warn('first line\\n  second line', RuntimeWarning)")
    assert done.returncode == 0, done.stderr
    assert done.stderr == "controlgs plugins: warning: first line second line\n"


def test_a_library_warning_names_no_file():
    done = _cli_in_a_fresh_process("warn_user('the capture is odd', UserWarning)")
    assert done.returncode == 0, done.stderr
    assert done.stderr == "controlgs plugins: warning: the capture is odd\n"


def test_a_caller_recording_warnings_still_gets_them(monkeypatch, capsys):
    _warning_command(monkeypatch, lambda: warnings.warn("kept", RuntimeWarning))
    with pytest.warns(RuntimeWarning, match="kept"):
        assert cli.main(["plugins"]) == 0
    assert capsys.readouterr().err == ""


def test_warn_user_skips_only_the_librarys_own_folders():
    from controlgs_adapter.errors import _OWN, _between

    assert any(p.endswith("controlgs_adapter/") for p in _OWN)
    assert _between(cli.__file__) and not _between(__file__)


def test_library_warnings_land_on_the_users_line():
    from controlgs_adapter.downstream.optics.stage import PSFOptics

    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        PSFOptics(stretch=True)
    assert [w.category for w in caught] == [DeprecationWarning] and caught[0].filename == __file__


@pytest.mark.parametrize("category", [RuntimeWarning, UserWarning])
def test_warn_user_keeps_the_category(category):
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        warn_user("x", category)
    assert caught[0].category is category and caught[0].filename == __file__
