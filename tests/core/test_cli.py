"""Tests of ``controlgs_adapter.cli``: every option of every command (name, default, type, choices, help text),
a refused command in a fresh process (one line, no traceback), and warnings printed as one line for the
duration of a command; library warnings point at the Python caller's line."""

from __future__ import annotations

import argparse
import functools
import subprocess
import sys
import types
import warnings
from pathlib import Path
from typing import Any

import pytest
from helpers.cli_runs import error_line

import controlgs_adapter.report as report_module
from controlgs_adapter import cli
from controlgs_adapter._version import __version__
from controlgs_adapter.cli import main
from controlgs_adapter.commands import plugins as plugins_command

ROOT = Path(__file__).resolve().parents[2]


def test_cli_error_in_a_fresh_process_has_no_traceback():
    r = subprocess.run([sys.executable, "-m", "controlgs_adapter.cli", "optics", "build-bank", "--psf-size", "4"],
                       capture_output=True, text=True, cwd=ROOT, timeout=120)
    assert r.returncode == 2 and "Traceback" not in r.stderr and len(r.stderr.strip().splitlines()) == 1, r.stderr


# ------------------------------------------------------------------------------ parser
def test_usage_names_the_sub_command_as_COMMAND():
    usage = cli.build_parser().format_usage()
    assert "COMMAND" in usage and "{plugins" not in usage, usage


# (command, option, dest, action, type, choices, default, metavar, nargs, required)
OPTIONS: list[tuple[str, str, str, str, str, list[str] | tuple[str, ...] | None, Any, Any, Any, bool]] = [
    ('plugins', '--strict', 'strict', 'true', 'str', None, False, None, 0, False),
    ('optics build-bank', '--lens', 'lens', 'store', 'str', None, 'cardboard', 'LENS', None, False),
    ('optics build-bank', '--out', 'out', 'store', 'Path', None, Path('psf_bank.safetensors'), None, None, False),
    ('optics build-bank', '--grid', 'grid', 'store', 'int', None, (30, 30), ('GY', 'GX'), 2, False),
    ('optics build-bank', '--psf-size', 'psf_size', 'store', 'int', None, 33, None, None, False),
    ('optics build-bank', '--pupil-samples', 'pupil_samples', 'store', 'int', None, 192, None, None, False),
    ('optics build-bank', '--min-pitch-px', 'min_pitch_px', 'store', 'float', None, 0.125, None, None, False),
    ('optics figures', '--lens', 'lens', 'store', 'str', None, 'cardboard', 'LENS', None, False),
    ('optics bench', '--sizes', 'sizes', 'store', 'str', None, ['256', '512', '1024', '576x1024'], None, '+', False),
    ('optics bench', '--radiometry', 'radiometry', 'store', 'str', ['radiance', 'energy'], ['radiance', 'energy'], None, '+', False),
    ('optics bench', '--tols', 'tols', 'store', 'float', None, [0.02], None, '+', False),
    ('optics bench', '--repeat', 'repeat', 'store', 'int', None, 3, None, None, False),
    ('optics bench', '--no-scaling', 'scaling', 'false', 'str', None, True, None, 0, False),
    ('optics bench', '--zone', 'zone', 'store', 'int', None, 5, None, None, False),
    ('optics bench', '--exact-max', 'exact_max', 'store', 'int', None, 1024, None, None, False),
    ('optics bench', '--threads', 'threads', 'store', 'int', None, 2, None, None, False),
    ('optics bench', '--out', 'out', 'store', 'Path', None, None, None, None, False),
    ('optics bench', '--doc', 'out', 'const', 'str', None, None, None, 0, False),
    ('optics fit-prewarp', '--lens', 'lens', 'store', 'str', None, 'cardboard', 'LENS', None, False),
    ('optics fit-prewarp', '--out', 'out', 'store', 'Path', None, None, None, None, True),
    ('optics fit-prewarp', '--size', 'size', 'store', 'int', None, [64, 96, 128, 192, 256], None, '+', False),
    ('optics fit-prewarp', '--modes', 'modes', 'store', 'str', ['distortion', 'exact', 'fast'], ['distortion', 'exact'], None, '+', False),
    ('optics fit-prewarp', '--radiometry', 'radiometry', 'store', 'str', ['radiance', 'energy'], 'radiance', None, None, False),
    ('backbone train', '--data', 'data', 'store', 'str', None, None, None, None, True),
    ('backbone train', '--out', 'out', 'store', 'str', None, None, None, None, True),
    ('backbone train', '--resolution', 'resolution', 'store', 'int', None, 256, None, None, False),
    ('backbone train', '--iterations', 'iterations', 'store', 'int', None, 1500, None, None, False),
    ('backbone train', '--max-anchors', 'max_anchors', 'store', 'int', None, 3000, None, None, False),
    ('backbone train', '--seed', 'seed', 'store', 'int', None, 0, None, None, False),
    ('backbone train', '--device', 'device', 'store', 'str', None, 'cpu', None, None, False),
    ('backbone train', '--format', 'format', 'store', 'str', ['colmap', 'blender', 'instant_ngp'], None, None, None, False),
    ('backbone train', '--images', 'images', 'store', 'str', None, None, None, None, False),
    ('backbone train', '--holdout', 'holdout', 'store', 'int', None, 8, None, None, False),
    ('backbone train', '--white-background', 'white_background', 'true', 'str', None, False, None, 0, False),
    ('backbone train', '--no-progress', 'progress', 'false', 'str', None, True, None, 0, False),
    ('scene build-backbone', '--variant', 'variant', 'store', 'str', ['ar', 'vr'], 'ar', None, None, False),
    ('scene build-backbone', '--resolution', 'resolution', 'store', 'int', None, 128, None, None, False),
    ('scene build-backbone', '--iterations', 'iterations', 'store', 'int', None, 1500, None, None, False),
    ('scene build-backbone', '--max-anchors', 'max_anchors', 'store', 'int', None, 3000, None, None, False),
    ('scene build-backbone', '--n-offsets', 'n_offsets', 'store', 'int', None, 5, None, None, False),
    ('scene build-backbone', '--out', 'out', 'store', 'str', None, None, None, None, True),
    ('scene build-backbone', '--seed', 'seed', 'store', 'int', None, 0, None, None, False),
    ('scene export', '--variant', 'variant', 'store', 'str', ['ar', 'vr'], 'ar', None, None, False),
    ('scene export', '--resolution', 'resolution', 'store', 'int', None, 128, None, None, False),
    ('scene export', '--out', 'out', 'store', 'str', None, None, None, None, True),
    ('train', '--out', 'out', 'store', 'str', None, 'controlgs-run', None, None, False),
    ('train', '--variant', 'variant', 'store', 'str', ['ar', 'vr'], 'ar', None, None, False),
    ('train', '--resolution', 'resolution', 'store', 'int', None, None, None, None, False),
    ('train', '--test-views', 'test_views', 'store', 'int', None, None, None, None, False),
    ('train', '--optics', 'optics', 'store', 'str', ['fast', 'exact'], 'fast', None, None, False),
    ('train', '--seed', 'seed', 'store', 'int', None, 0, None, None, False),
    ('train', '--seeds', 'seeds', 'store', 'int', None, None, None, None, False),
    ('train', '--no-progress', 'progress', 'false', 'str', None, True, None, 0, False),
    ('train', '--lens', 'lens', 'store', 'str', None, None, 'LENS', None, False),
    ('train', '--effects', 'effects', 'store', 'str', None, None, None, None, False),
    ('train', '--iterations', 'iterations', 'store', 'int', None, 1000, None, None, False),
    ('train', '--psf-fraction', 'psf_fraction', 'store', 'float', None, 0.1, None, None, False),
    ('train', '--lr', 'lr', 'store', 'float', None, 0.003, None, None, False),
    ('train', '--gaze-jitter-deg', 'gaze_jitter_deg', 'store', 'float', None, 0.0, None, None, False),
    ('train', '--cond-dim', 'cond_dim', 'store', 'int', None, 8, None, None, False),
    ('train', '--lens-conditioning', 'lens_conditioning', 'store', 'str', ('radius', 'xy'), None, None, None, False),
    ('train', '--checkpoint-every', 'checkpoint_every', 'store', 'int', None, 500, None, None, False),
    ('train', '--model', 'model', 'store', 'str', None, None, None, None, False),
    ('train', '--data', 'data', 'store', 'str', None, None, None, None, False),
    ('train', '--family', 'family', 'store', 'str', ['scaffold_gs', 'octree_gs', 'hac', 'contextgs', 'compgs'], None, None, None, False),
    ('train', '--model-iteration', 'model_iteration', 'store', 'int', None, None, None, None, False),
    ('train', '--allow-unquantized', 'allow_unquantized', 'true', 'str', None, None, None, 0, False),
    ('train', '--format', 'format', 'store', 'str', ['colmap', 'blender', 'instant_ngp'], None, None, None, False),
    ('train', '--images', 'images', 'store', 'str', None, None, None, None, False),
    ('train', '--holdout', 'holdout', 'store', 'int', None, None, None, None, False),
    ('train', '--white-background', 'white_background', 'true', 'str', None, None, None, 0, False),
    ('train', '--cache-mib', 'cache_mib', 'store', 'int', None, 1024, None, None, False),
    ('train', '--device', 'device', 'store', 'str', None, 'cpu', None, None, False),
    ('train', '--rasterizer', 'rasterizer', 'store', 'str', None, None, 'NAME', None, False),
    ('train', '--renderer', 'renderer', 'store', 'str', None, None, 'MODULE:ATTR', None, False),
    ('train', '--batch-size', 'batch_size', 'store', 'int', None, 1, None, None, False),
    ('train', '--scenes', 'scenes', 'store', 'str', ['ar', 'vr'], None, 'SCENE', '+', False),
    ('train', '--dist-backend', 'dist_backend', 'store', 'str', ['gloo', 'nccl'], None, None, None, False),
    ('train', '--dist-timeout', 'dist_timeout', 'store', 'float', None, 300.0, None, None, False),
    ('train', '--exchange', 'exchange', 'store', 'str', ['auto', 'sparse', 'dense'], 'auto', None, None, False),
    ('train', '--ablations', 'ablations', 'bool', 'str', None, True, None, 0, False),
    ('train', '--ablation', 'ablation', 'append', 'str', ['wo_lens', 'wo_display', 'wo_resample', 'state_blind'], [], None, None, False),
    ('eval', '--run', 'run', 'store', 'str', None, 'controlgs-run', None, None, False),
    ('eval', '--out', 'out', 'store', 'str', None, None, None, None, False),
    ('eval', '--variant', 'variant', 'store', 'str', ['ar', 'vr'], 'ar', None, None, False),
    ('eval', '--resolution', 'resolution', 'store', 'int', None, None, None, None, False),
    ('eval', '--test-views', 'test_views', 'store', 'int', None, None, None, None, False),
    ('eval', '--optics', 'optics', 'store', 'str', ['fast', 'exact'], 'fast', None, None, False),
    ('eval', '--seed', 'seed', 'store', 'int', None, 0, None, None, False),
    ('eval', '--seeds', 'seeds', 'store', 'int', None, None, None, None, False),
    ('eval', '--no-progress', 'progress', 'false', 'str', None, True, None, 0, False),
    ('eval', '--lens', 'lens', 'store', 'str', None, None, 'LENS', None, False),
    ('eval', '--gazes', 'gazes', 'store', 'str', None, None, 'AZ,EL', '+', False),
    ('eval', '--model', 'model', 'store', 'str', None, None, None, None, False),
    ('eval', '--data', 'data', 'store', 'str', None, None, None, None, False),
    ('eval', '--family', 'family', 'store', 'str', ['scaffold_gs', 'octree_gs', 'hac', 'contextgs', 'compgs'], None, None, None, False),
    ('eval', '--model-iteration', 'model_iteration', 'store', 'int', None, None, None, None, False),
    ('eval', '--allow-unquantized', 'allow_unquantized', 'true', 'str', None, None, None, 0, False),
    ('eval', '--format', 'format', 'store', 'str', ['colmap', 'blender', 'instant_ngp'], None, None, None, False),
    ('eval', '--images', 'images', 'store', 'str', None, None, None, None, False),
    ('eval', '--holdout', 'holdout', 'store', 'int', None, None, None, None, False),
    ('eval', '--white-background', 'white_background', 'true', 'str', None, None, None, 0, False),
    ('eval', '--cache-mib', 'cache_mib', 'store', 'int', None, 1024, None, None, False),
    ('eval', '--device', 'device', 'store', 'str', None, 'cpu', None, None, False),
    ('eval', '--rasterizer', 'rasterizer', 'store', 'str', None, None, 'NAME', None, False),
    ('eval', '--renderer', 'renderer', 'store', 'str', None, None, 'MODULE:ATTR', None, False),
    ('eval', '--trust-run-renderer', 'trust_run_renderer', 'true', 'str', None, False, None, 0, False),
    ('eval', '--effects', 'effects', 'store', 'str', None, None, None, None, False),
    ('eval', '--lpips-weights', 'lpips_weights', 'store', 'str', None, None, 'PATH', '+', False),
    ('demo', '--out', 'out', 'store', 'str', None, 'report', None, None, False),
    ('demo', '--variant', 'variant', 'store', 'str', ['ar', 'vr'], 'ar', None, None, False),
    ('demo', '--resolution', 'resolution', 'store', 'int', None, None, None, None, False),
    ('demo', '--test-views', 'test_views', 'store', 'int', None, None, None, None, False),
    ('demo', '--optics', 'optics', 'store', 'str', ['fast', 'exact'], 'fast', None, None, False),
    ('demo', '--seed', 'seed', 'store', 'int', None, 0, None, None, False),
    ('demo', '--seeds', 'seeds', 'store', 'int', None, None, None, None, False),
    ('demo', '--no-progress', 'progress', 'false', 'str', None, True, None, 0, False),
    ('demo', '--lens', 'lens', 'store', 'str', None, None, 'LENS', None, False),
    ('demo', '--gazes', 'gazes', 'store', 'str', None, None, 'AZ,EL', '+', False),
    ('demo', '--effects', 'effects', 'store', 'str', None, None, None, None, False),
    ('demo', '--iterations', 'iterations', 'store', 'int', None, 1000, None, None, False),
    ('demo', '--psf-fraction', 'psf_fraction', 'store', 'float', None, 0.1, None, None, False),
    ('demo', '--lr', 'lr', 'store', 'float', None, 0.003, None, None, False),
    ('demo', '--gaze-jitter-deg', 'gaze_jitter_deg', 'store', 'float', None, 0.0, None, None, False),
    ('demo', '--cond-dim', 'cond_dim', 'store', 'int', None, 8, None, None, False),
    ('demo', '--lens-conditioning', 'lens_conditioning', 'store', 'str', ('radius', 'xy'), None, None, None, False),
    ('demo', '--checkpoint-every', 'checkpoint_every', 'store', 'int', None, 500, None, None, False),
    ('demo', '--lpips-weights', 'lpips_weights', 'store', 'str', None, None, 'PATH', '+', False),
    ('demo', '--ablations', 'ablations', 'bool', 'str', None, True, None, 0, False),
    ('bench', '--out', 'out', 'store', 'Path', None, None, None, None, False),
    ('bench', '--doc', 'out', 'const', 'str', None, None, None, 0, False),
    ('bench', '--resolution', 'resolution', 'store', 'int', None, 96, None, None, False),
    ('bench', '--iterations', 'iterations', 'store', 'int', None, None, None, None, False),
    ('bench', '--test-views', 'test_views', 'store', 'int', None, None, None, None, False),
    ('bench', '--quick', 'quick', 'true', 'str', None, False, None, 0, False),
    ('bench', '--variant', 'variant', 'store', 'str', ['ar', 'vr'], 'ar', None, None, False),
    ('bench', '--seed', 'seed', 'store', 'int', None, 0, None, None, False),
    ('bench', '--no-progress', 'progress', 'false', 'str', None, True, None, 0, False),
    ('view', '--run', 'run', 'store', 'str', None, None, None, None, False),
    ('view', '--port', 'port', 'store', 'int', None, 0, None, None, False),
    ('view', '--variant', 'variant', 'store', 'str', ['ar', 'vr'], 'ar', None, None, False),
    ('view', '--resolution', 'resolution', 'store', 'int', None, None, None, None, False),
    ('view', '--test-views', 'test_views', 'store', 'int', None, None, None, None, False),
    ('view', '--iterations', 'iterations', 'store', 'int', None, 150, None, None, False),
    ('view', '--threads', 'threads', 'store', 'int', None, None, None, None, False),
    ('view', '--lens', 'lens', 'store', 'str', None, None, 'LENS', None, False),
    ('view', '--model', 'model', 'store', 'str', None, None, None, None, False),
    ('view', '--data', 'data', 'store', 'str', None, None, None, None, False),
    ('view', '--family', 'family', 'store', 'str', ['scaffold_gs', 'octree_gs', 'hac', 'contextgs', 'compgs'], None, None, None, False),
    ('view', '--model-iteration', 'model_iteration', 'store', 'int', None, None, None, None, False),
    ('view', '--allow-unquantized', 'allow_unquantized', 'true', 'str', None, None, None, 0, False),
    ('view', '--format', 'format', 'store', 'str', ['colmap', 'blender', 'instant_ngp'], None, None, None, False),
    ('view', '--images', 'images', 'store', 'str', None, None, None, None, False),
    ('view', '--holdout', 'holdout', 'store', 'int', None, None, None, None, False),
    ('view', '--white-background', 'white_background', 'true', 'str', None, None, None, 0, False),
    ('view', '--cache-mib', 'cache_mib', 'store', 'int', None, 1024, None, None, False),
    ('view', '--device', 'device', 'store', 'str', None, 'cpu', None, None, False),
    ('view', '--rasterizer', 'rasterizer', 'store', 'str', None, None, 'NAME', None, False),
    ('view', '--renderer', 'renderer', 'store', 'str', None, None, 'MODULE:ATTR', None, False),
    ('view', '--trust-run-renderer', 'trust_run_renderer', 'true', 'str', None, False, None, 0, False),
]


#: the value a flag stores
CONSTS: dict[tuple[str, str], Any] = {("optics bench", "--doc"): Path("docs/benchmarks"),
                                      ("bench", "--doc"): Path("docs/benchmarks/accuracy-time.md")}


#: options a command needs to parse at all
REQUIRED_ARGS: dict[str, list[str]] = {"optics fit-prewarp": ["--out", "lut.safetensors"],
                                       "scene build-backbone": ["--out", "o"], "scene export": ["--out", "o"],
                                       "backbone train": ["--data", "d", "--out", "o"]}


@functools.lru_cache(maxsize=1)
def _parser() -> argparse.ArgumentParser:
    return cli.build_parser()  # parsing does not change it: one for the file


def _parse(command: str, *argv: str, fill: bool = True) -> argparse.Namespace:
    need = REQUIRED_ARGS.get(command, [])
    extra = [x for o, v in zip(need[::2], need[1::2]) if fill and o not in argv for x in (o, v)]
    return _parser().parse_args([*command.split(), *extra, *argv])


def _refused(capsys: pytest.CaptureFixture[str], command: str, *argv: str, fill: bool = True) -> str:
    with pytest.raises(SystemExit) as e:
        _parse(command, *argv, fill=fill)
    assert e.value.code == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err[0].startswith("usage: controlgs " + command), err
    return err[-1]


def _help(command: str) -> str:
    parser = _parser()
    for name in command.split():
        sub = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
        parser = sub.choices[name]
    return " ".join(parser.format_help().split())


_IDS = [f"{c}:{o}" for c, o, *_ in OPTIONS]


@pytest.mark.parametrize("command, option, dest, action, typ, choices, default, metavar, nargs, required", OPTIONS, ids=_IDS)
def test_option(command, option, dest, action, typ, choices, default, metavar, nargs, required, capsys):
    help_text = _help(command)
    if required:
        msg = _refused(capsys, command, fill=False)
        needed = [o for c, o, *_, r in OPTIONS if c == command and r]
        assert msg.startswith(f"controlgs {command}: error: ") and "required" in msg, msg
        assert all(o in msg for o in needed), msg  # every required option is named
    else:  # the default reaches the namespace as written (value and type)
        got = getattr(_parse(command), dest)
        assert got == default and type(got) is type(default), (got, default)
    if action == "store":
        if metavar is not None:  # the help shows it after the option
            shown = " ".join(metavar) if isinstance(metavar, tuple) else metavar
            assert f"{option} {shown}" in help_text, help_text
        n = 2 if nargs == 2 else 1
        if typ in ("int", "float"):
            msg = _refused(capsys, command, option, *["x1"] * n)
            assert msg.startswith(f"controlgs {command}: error: argument {option}: ") and typ in msg and "'x1'" in msg, msg
            value = getattr(_parse(command, option, *["7"] * n), dest)
            want: Any = [int("7") if typ == "int" else 7.0] * n
            assert value == (want if isinstance(nargs, (int, str)) else want[0])
            assert all(type(v) is type(want[0]) for v in (value if isinstance(value, list) else [value]))
        elif typ == "Path":
            assert getattr(_parse(command, option, "a/b.x"), dest) == Path("a/b.x")
        elif choices is None:  # a plain string, kept as given
            value = getattr(_parse(command, option, "a:b"), dest)
            assert value == (["a:b"] if nargs == "+" else "a:b")
        if nargs == "+":  # several values
            vals = choices[:2] if choices else (["1", "2"] if typ == "str" else ["7", "8"])
            assert len(getattr(_parse(command, option, *vals), dest)) == len(vals)
        if nargs == 2:
            msg = _refused(capsys, command, option, "7")
            assert msg.startswith(f"controlgs {command}: error: argument {option}: ") and "2" in msg, msg
    if choices is not None:
        msg = _refused(capsys, command, option, "bogus")
        assert msg.startswith(f"controlgs {command}: error: argument {option}: ") and "'bogus'" in msg, msg
        assert all(c in msg.split("'bogus'", 1)[1] for c in choices), msg  # the choices are listed
        for c in choices:
            value = getattr(_parse(command, option, c), dest)
            assert value == ([c] if action == "append" or nargs == "+" else c)
    if action == "true":
        assert getattr(_parse(command, option), dest) is True
    elif action == "false":
        assert getattr(_parse(command, option), dest) is False
    elif action == "const":
        assert getattr(_parse(command, option), dest) == CONSTS[command, option]
    elif action == "bool":
        assert getattr(_parse(command, option), dest) is True
        assert getattr(_parse(command, "--no-" + option[2:]), dest) is False
    elif action == "append":
        assert getattr(_parse(command, option, choices[0], option, choices[-1]), dest) == [choices[0], choices[-1]]
    assert option in help_text


def test_table_lists_every_option():
    # an option added without a row here (or a row for one removed) fails: the table stays complete
    parser = cli.build_parser()
    seen = set()

    def walk(p: argparse.ArgumentParser, prefix: str) -> None:
        for a in p._actions:
            if isinstance(a, argparse._SubParsersAction):
                for name, sp in a.choices.items():
                    walk(sp, f"{prefix} {name}".strip())
            elif a.option_strings and not isinstance(a, (argparse._HelpAction, argparse._VersionAction)):
                seen.add((prefix, a.option_strings[0]))

    walk(parser, "")
    assert seen == {(c, o) for c, o, *_ in OPTIONS}


def test_every_option_is_described_in_the_help():
    # each option's --help line carries a description (a dropped help= leaves the bare option)
    for command, option, *_ in OPTIONS:
        parser = _parser()
        for name in command.split():
            parser = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction)).choices[name]
        action = next(a for a in parser._actions if option in a.option_strings)
        described = parser._get_formatter()._expand_help(action) if action.help else ""
        assert len(described.split()) >= 2, (command, option, action.help)
        assert " ".join(described.split()[:2]) in _help(command), (command, option)  # printed by --help


def test_every_command_action_and_option_has_a_help_text():
    """``controlgs --help`` and each sub-command's ``--help`` describe everything they offer."""
    undocumented: list[str] = []

    def walk(p: argparse.ArgumentParser, path: list[str]) -> int:
        n = 0
        for a in p._actions:
            if isinstance(a, argparse._SubParsersAction):
                for ca in a._choices_actions:
                    n += 1
                    if not ca.help:
                        undocumented.append(" ".join(path + [ca.dest]))
                for name, sp in a.choices.items():
                    n += walk(sp, path + [name])
            elif not isinstance(a, argparse._HelpAction):
                n += 1
                if not a.help:
                    undocumented.append(" ".join(path + [a.option_strings[0] if a.option_strings else a.dest]))
        return n

    assert walk(cli.build_parser(), []) > 150  # every command, action and option was visited
    assert undocumented == []


# ------------------------------------------------------------------------------ warnings
def test_warnings_are_one_line_naming_the_command_in_a_fresh_process():
    """Run from a shell (a fresh interpreter, no test harness recording warnings), ``controlgs plugins``
    whose run warns twice prints each warning as one line ``controlgs plugins: warning: <message>``: a
    multi-line message joined, a library warning without its file; the formatting is put back after."""
    code = ("import sys, warnings\n"
            "from controlgs_adapter import cli\n"
            "from controlgs_adapter.commands import plugins\n"
            "from controlgs_adapter.errors import warn_user\n"
            "plugins.run = lambda args: (warnings.warn('first line\\n  second line', RuntimeWarning),\n"
            "                            warn_user('the capture is odd', UserWarning), 0)[-1]\n"
            "before = warnings.formatwarning\n"
            "code = cli.main(['plugins'])\n"
            "assert warnings.formatwarning is before\n"
            "sys.exit(code)\n")
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr
    assert done.stderr == ("controlgs plugins: warning: first line second line\n"
                           "controlgs plugins: warning: the capture is odd\n")


def test_a_caller_recording_warnings_still_gets_them(monkeypatch, capsys):
    def run(args: argparse.Namespace) -> int:
        warnings.warn("kept", RuntimeWarning)
        return 0

    monkeypatch.setattr(plugins_command, "run", run)
    with pytest.warns(RuntimeWarning, match="kept"):
        assert cli.main(["plugins"]) == 0
    assert capsys.readouterr().err == ""


def test_commands_are_registered_in_order() -> None:
    assert cli.COMMANDS == ("plugins", "optics", "scene", "backbone", "train", "eval", "demo", "bench", "view")


_DEMO_HINT = "which is not installed: pip install 'controlgs-adapter[demo]'"


@pytest.mark.parametrize("stand_in", [types.ModuleType, None], ids=["no-file", "no-import"])
@pytest.mark.parametrize("argv,blocked,purpose,missing", [
    (["demo"], "skimage", "controlgs demo (the built-in scene and the report's plots)", "scikit-image"),
    (["optics", "bench"], "skimage", "controlgs optics bench (the optics benchmark's test image and plot)",
     "scikit-image"),
    (["scene", "export"], "skimage", "controlgs scene export (exporting the built-in scene's views as PNG)",
     "scikit-image"),
    (["eval", "--run", "RUN"], "matplotlib", "controlgs eval (the report's plots)", "matplotlib"),
    (["demo"], "matplotlib", "controlgs demo (the built-in scene and the report's plots)", "matplotlib"),
])
def test_a_missing_extra_is_refused_before_any_work(tmp_path, monkeypatch, capsys, argv, blocked, purpose, missing,
                                                    stand_in):
    """A package that does not import, or a stand-in module without a file (extras.py), counts as missing: the
    command stops before its work naming the extra to install."""
    monkeypatch.setitem(sys.modules, blocked, None if stand_in is None else stand_in(blocked))
    out = tmp_path / "out"
    argv = [str(tmp_path / "run") if a == "RUN" else a for a in argv] + ["--out", str(out)]
    assert main(argv) == 2
    assert error_line(capsys, argv[0]) == f"{purpose} needs {missing}, {_DEMO_HINT}"
    assert not out.exists()


def test_eval_needs_matplotlib_only(capsys, monkeypatch, tmp_path):
    """eval's entry in the table of optional packages names matplotlib alone: without scikit-image it goes on to
    its own check of the run folder; optics figures needs neither."""
    for stand_in in (types.ModuleType("skimage"), None):  # a module without a file, or one that does not import
        monkeypatch.setitem(sys.modules, "skimage", stand_in)
        assert main(["eval", "--run", str(tmp_path / "no-run"), "--out", str(tmp_path / "out")]) == 2
        line = error_line(capsys, "eval")
        assert "scikit-image" not in line and "no-run" in line, line
    assert main(["eval", "--run", str(tmp_path)]) == 2
    assert error_line(capsys, "eval") == (f"{tmp_path}: no controlgs.controlgs.safetensors (train one with "
                                          f"`controlgs train --out {tmp_path}`)")
    # optics figures needs neither
    assert main(["optics", "figures", "--lens", str(tmp_path / "none.json")]) == 2
    assert error_line(capsys, "optics") == (f"--lens {tmp_path / 'none.json'}: no such file "
                                            "(nor a shipped lens: cardboard, compact)")
    monkeypatch.setitem(sys.modules, "matplotlib", types.ModuleType("matplotlib"))
    assert main(["eval", "--run", str(tmp_path)]) == 2
    assert error_line(capsys, "eval").startswith("controlgs eval (the report's plots) needs matplotlib")


def test_cli_import_errors_outside_the_table_are_one_line(tmp_path, monkeypatch, capsys):
    """A package missing at the command's own import (not in REQUIRES) and a broken install (a name
    missing from a module) each end in one line and exit code 2, never a traceback."""
    pytest.importorskip("matplotlib")
    argv = ["eval", "--run", str(tmp_path / "run"), "--out", str(tmp_path / "out")]
    with monkeypatch.context() as mp:
        mp.setitem(sys.modules, "controlgs_adapter.report", None)
        assert main(argv) == 2
    err = capsys.readouterr().err
    assert err == ("controlgs eval: error: needs the Python package 'controlgs_adapter.report', which is not installed "
                   "(pip install 'controlgs-adapter[demo]' installs the optional ones)\n"), err
    monkeypatch.delattr(report_module, "write_report")
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert err.startswith("controlgs eval: error: cannot import name 'write_report' from 'controlgs_adapter.report'"), err
    assert err.endswith(" (pip install 'controlgs-adapter[demo]' installs the optional ones)\n") and err.count("\n") == 1


def test_main_help_version_and_errors(capsys, tmp_path):
    assert main([]) == 0 and "usage: controlgs" in capsys.readouterr().out
    with pytest.raises(SystemExit) as e:
        main(["--version"])
    assert e.value.code == 0
    assert capsys.readouterr().out.strip() == f"controlgs-adapter {__version__}"
    # an unreadable file is one line naming the option and the file, exit 2
    if Path("/proc/self/mem").is_file():
        assert main(["optics", "figures", "--lens", "/proc/self/mem"]) == 2
        assert error_line(capsys, "optics").startswith("--lens /proc/self/mem: not readable: ")


def test_main_missing_module_is_one_line(capsys, monkeypatch):
    # a module that cannot be imported: the package named, with the extra to install
    monkeypatch.setitem(sys.modules, "controlgs_adapter.downstream.optics.generate", None)
    assert main(["optics", "figures"]) == 2
    msg = error_line(capsys, "optics")
    assert msg == ("needs the Python package 'controlgs_adapter.downstream.optics.generate', which is not installed "
                   "(pip install 'controlgs-adapter[demo]' installs the optional ones)")
    # another ImportError (a name missing from a module): its own message on one line
    monkeypatch.setitem(sys.modules, "controlgs_adapter.downstream.optics.generate", types.ModuleType("standin"))
    assert main(["optics", "figures"]) == 2
    msg = error_line(capsys, "optics")
    assert msg == ("cannot import name 'lens_figures' from 'standin' (unknown location) (pip install "
                   "'controlgs-adapter[demo]' installs the optional ones)")


def test_an_error_message_with_a_newline_is_one_line(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """torch's message repeats the raw device string: the CLI still prints one line."""
    assert main(["train", "--model", "m", "--data", "d", "--out", str(tmp_path / "r"), "--device", "cu\nda"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("controlgs train: error: --device 'cu\\nda': "), err


def test_warnings_as_lines_prints_each_warning_as_one_line_and_restores_the_formatter(capsys):
    """Inside the block a warning Python prints is one line naming the command (its message's
    whitespace folded, no file, line or source); ``warnings.formatwarning`` is put back after."""
    import warnings

    from controlgs_adapter.cli import warnings_as_lines

    before = warnings.formatwarning
    with warnings_as_lines("train"):  # pytest records warnings itself: call the formatter Python would call
        assert warnings.formatwarning("two\n   lines", UserWarning, "lib.py", 3) == ""
    assert capsys.readouterr().err == "controlgs train: warning: two lines\n"
    assert warnings.formatwarning is before
