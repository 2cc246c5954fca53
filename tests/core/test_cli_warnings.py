"""The command line prints a warning as one line ``controlgs <cmd>: warning: <message>`` (no file, line or
source), for the duration of the command only; library warnings point at the Python caller's line."""

from __future__ import annotations

import argparse
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


def test_a_warning_is_one_line_naming_the_command(monkeypatch, capsys):
    _warning_command(monkeypatch, lambda: warnings.warn("first line\n  second line", RuntimeWarning))
    before = warnings.showwarning
    with warnings.catch_warnings():
        warnings.simplefilter("always")
        assert cli.main(["plugins"]) == 0
    err = capsys.readouterr().err
    assert err == "controlgs plugins: warning: first line second line\n"
    assert warnings.showwarning is before  # put back after the command


def test_a_library_warning_names_no_library_file(monkeypatch, capsys):
    _warning_command(monkeypatch, lambda: warn_user("the capture is odd", UserWarning))
    with warnings.catch_warnings():
        warnings.simplefilter("always")
        assert cli.main(["plugins"]) == 0
    err = capsys.readouterr().err
    assert err == "controlgs plugins: warning: the capture is odd\n" and ".py" not in err


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
