"""``controlgs optics build-bank`` / ``fit-prewarp`` / ``bench`` check ``--out`` before the work: a
folder where the file goes or a file in the way of its folder is one line, and nothing is traced."""

from __future__ import annotations

from pathlib import Path

import pytest
from helpers.cli_runs import error_line

from controlgs_adapter.cli import main


@pytest.fixture
def no_work(monkeypatch: pytest.MonkeyPatch) -> None:
    import controlgs_adapter.downstream.optics.bench as bench
    import controlgs_adapter.downstream.optics.generate as generate
    import controlgs_adapter.downstream.prewarp_fit as prewarp_fit

    def refuse(*args: object, **kwargs: object) -> None:
        raise AssertionError("the work started")

    monkeypatch.setattr(generate, "build_bank", refuse)
    monkeypatch.setattr(prewarp_fit, "fit_bank_prewarp", refuse)
    monkeypatch.setattr(bench, "run", refuse)


@pytest.mark.parametrize("action", [["build-bank"], ["fit-prewarp"]])
def test_a_file_output_under_a_file_is_refused(tmp_path: Path, capsys: pytest.CaptureFixture[str], no_work: None,
                                               action: list[str]) -> None:
    blocker = tmp_path / "blocker"
    blocker.write_text("mine")
    out = blocker / "bank.safetensors"
    assert main(["optics", *action, "--out", str(out)]) == 2
    assert error_line(capsys, "optics") == f"--out {out}: {blocker} is a file, not a folder"
    assert main(["optics", *action, "--out", str(tmp_path)]) == 2
    assert error_line(capsys, "optics") == f"--out {tmp_path}: is a folder; expected the path of a file to write"
    assert blocker.read_text() == "mine"


def test_bench_out_that_is_a_file_is_refused(tmp_path: Path, capsys: pytest.CaptureFixture[str], no_work: None) -> None:
    taken = tmp_path / "taken"
    taken.write_text("mine")
    assert main(["optics", "bench", "--sizes", "16", "--out", str(taken)]) == 2
    assert error_line(capsys, "optics") == f"--out {taken}: is a file; expected a folder to write into"
    assert taken.read_text() == "mine"


import json
import os
import shutil
import sys
import threading
import types
from typing import Any

from helpers.adapters import random_adapter
from helpers.banks import tiny_bank

from controlgs_adapter import cli
from controlgs_adapter.downstream.optics.bank import PSFBank
from controlgs_adapter.evaluation import evaluate_grid
from controlgs_adapter.scene import builtin_backbone_dir, load_builtin_backbone, load_builtin_scene
from controlgs_adapter.viewer import ViewerSession, make_server

pytest.importorskip("matplotlib")

pytest.importorskip("skimage")



# ============================================================================ CLI
def _cli(argv: list[str], capsys: pytest.CaptureFixture[str]) -> str:
    """Run the CLI in-process: exit code 2, exactly one line on stderr, no traceback; returns it."""
    code = cli.main(argv)
    err = capsys.readouterr().err
    assert code == 2, (code, err)
    lines = err.strip().splitlines()
    assert len(lines) == 1 and "Traceback" not in err, err
    return lines[0]


def test_cli_full_disk_is_one_line(tmp_path, capsys, monkeypatch):
    import errno

    def full(data: Any, tmp: str, metadata: Any = None) -> None:
        Path(tmp).write_bytes(b"half")
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr("controlgs_adapter.formats.safetensors.save_file", full)
    monkeypatch.setattr("controlgs_adapter.downstream.optics.generate.build_bank", lambda *a, **k: tiny_bank())
    line = _cli(["optics", "build-bank", "--out", str(tmp_path / "b.safetensors")], capsys)
    assert "No space left" in line and "b.safetensors" in line
    assert not list(tmp_path.iterdir()), "no partial file left"


def test_optics_bench_page_names_the_command_line_it_was_given(tmp_path):
    """Called from Python (``cli.main(argv)``) as from a shell, the written page names the exact command
    line, quoted for a shell, so that it can be re-run."""
    import shlex

    from controlgs_adapter.cli import main

    out = tmp_path / "a dir"
    argv = ["optics", "bench", "--sizes", "16", "--radiometry", "radiance", "--repeat", "1", "--no-scaling",
            "--threads", "1", "--out", str(out)]
    assert main(argv) == 0
    page = (out / "optics_bench.md").read_text()
    command = page.split("Command: `", 1)[1].split("`", 1)[0]
    assert shlex.split(command) == ["controlgs", *argv]


def test_optics_bench_page_names_sys_argv_when_main_is_given_none(tmp_path, monkeypatch):
    """As the console script calls it (``main()``), the page names the shell's arguments after the
    program name: ``sys.argv[1:]``."""
    import shlex

    from controlgs_adapter.cli import main

    out = tmp_path / "b"
    argv = ["optics", "bench", "--sizes", "16", "--radiometry", "radiance", "--repeat", "1", "--no-scaling",
            "--threads", "1", "--out", str(out)]
    monkeypatch.setattr("sys.argv", ["/some/bin/controlgs", *argv])
    assert main() == 0
    page = (out / "optics_bench.md").read_text()
    command = page.split("Command: `", 1)[1].split("`", 1)[0]
    assert shlex.split(command) == ["controlgs", *argv]


# ------------------------------------------------------------------------------ optics build-bank
def test_build_bank_smallest_accepted_values(tmp_path, capsys):
    """The documented lower bounds are inclusive: ``--grid 1 1``, ``--psf-size 5`` (odd >= 5),
    ``--pupil-samples 4`` (>= 4) and a pitch below one pixel build a bank of that shape."""

    out = tmp_path / "b.safetensors"
    assert cli.main(["optics", "build-bank", "--grid", "1", "1", "--psf-size", "5", "--pupil-samples", "4",
                     "--min-pitch-px", "0.5", "--out", str(out)]) == 0
    assert capsys.readouterr().out.strip().splitlines()[-1].startswith(f"wrote {out} (")
    bank = PSFBank.load(out)
    assert tuple(bank.psf.shape) == (3, 1, 1, 5, 5)  # three primaries, 1 x 1 field, 5 x 5 samples


def _err(capsys: pytest.CaptureFixture[str], command: str) -> str:
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith(f"controlgs {command}: error: "), err
    return err[0][len(f"controlgs {command}: error: "):]


# ------------------------------------------------------------------------------ main()
def test_main_help_version_and_errors(capsys, tmp_path):
    assert cli.main([]) == 0 and "usage: controlgs" in capsys.readouterr().out
    with pytest.raises(SystemExit) as e:
        cli.main(["--version"])
    assert e.value.code == 0
    from controlgs_adapter._version import __version__

    assert capsys.readouterr().out.strip() == f"controlgs-adapter {__version__}"
    # an OSError (an unreadable file) is one line naming its type, exit 2
    if Path("/proc/self/mem").is_file():
        assert cli.main(["optics", "figures", "--prescription", "/proc/self/mem"]) == 2
        assert _err(capsys, "optics").startswith("OSError: ")


def test_main_missing_module_is_one_line(capsys, monkeypatch):
    # a module that cannot be imported: the package named, with the extra to install
    monkeypatch.setitem(sys.modules, "controlgs_adapter.downstream.optics.generate", None)
    assert cli.main(["optics", "figures"]) == 2
    msg = _err(capsys, "optics")
    assert msg == ("needs the Python package 'controlgs_adapter.downstream.optics.generate', which is not installed "
                   "(pip install 'controlgs-adapter[demo]' installs the optional ones)")
    # another ImportError (a name missing from a module): its own message on one line
    monkeypatch.setitem(sys.modules, "controlgs_adapter.downstream.optics.generate", types.ModuleType("standin"))
    assert cli.main(["optics", "figures"]) == 2
    msg = _err(capsys, "optics")
    assert msg == ("cannot import name 'lens_figures' from 'standin' (unknown location) (pip install "
                   "'controlgs-adapter[demo]' installs the optional ones)")


# ------------------------------------------------------------------------------ optics checks
@pytest.mark.parametrize("args, message", [
    (["--psf-size", "4"], "--psf-size must be an odd integer >= 5, got 4"),
    (["--psf-size", "3"], "--psf-size must be an odd integer >= 5, got 3"),
    (["--grid", "0", "5"], "--grid GY GX must both be >= 1, got 0 5"),
    (["--grid", "5", "0"], "--grid GY GX must both be >= 1, got 5 0"),
    (["--pupil-samples", "3"], "--pupil-samples must be >= 4, got 3"),
    (["--min-pitch-px", "0"], "--min-pitch-px must be a finite number > 0, got 0.0"),
    (["--min-pitch-px", "inf"], "--min-pitch-px must be a finite number > 0, got inf"),
    (["--min-pitch-px", "nan"], "--min-pitch-px must be a finite number > 0, got nan"),
    (["--prescription", "{d}/none.json"], "--prescription {d}/none.json: no such file"),
    (["--prescription", "{d}/bad.json"], "--prescription {d}/bad.json: not a JSON file: "),
    (["--prescription", "{d}/wrong.json"], "--prescription {d}/wrong.json: "),
])
def test_build_bank_refusals(capsys, tmp_path, args, message):
    (tmp_path / "bad.json").write_text("{not json")
    (tmp_path / "wrong.json").write_text('{"surfaces": 3}')
    d = str(tmp_path)
    argv = ["optics", "build-bank", "--out", f"{d}/b.safetensors", *[a.replace("{d}", d) for a in args]]
    assert cli.main(argv) == 2
    assert _err(capsys, "optics").startswith(message.replace("{d}", d))
    assert not (tmp_path / "b.safetensors").exists()


def test_optics_figures_prints_json(capsys):
    import json

    assert cli.main(["optics", "figures"]) == 0
    figures = json.loads(capsys.readouterr().out)
    assert figures["half_width_mm"] == 12.0  # Cardboard: a 24 mm wide display half
    assert figures["px_per_mm_display_at_1024"] == pytest.approx(1024 / 24.0)


def test_optics_bench_and_fit_prewarp_commands(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["optics", "bench", "--sizes", "16", "--radiometry", "radiance", "--repeat", "1", "--no-scaling",
                 "--exact-max", "16", "--threads", "1", "--out", str(tmp_path / "ob")]) == 0
    assert sorted(p.name for p in (tmp_path / "ob").iterdir()) == ["optics_bench.md", "optics_bench.png"]
    assert "16x16 radiance exact" in capsys.readouterr().out
    lut = tmp_path / "lut.safetensors"
    assert main(["optics", "fit-prewarp", "--size", "8", "--modes", "distortion", "--radiometry", "energy",
                 "--out", str(lut)]) == 0  # not the default radiometry: the option must reach the fit
    out = capsys.readouterr().out
    meta = json.loads(out[:out.rindex("}") + 1])
    assert (meta["size"], meta["radiometry"], list(meta["residuals"])) == ([8, 8], "energy", ["distortion"])
    assert lut.is_file() and out.strip().splitlines()[-1].startswith(f"wrote {lut} (")


SIZE = 64


CHROMIUM = shutil.which("chromium") or shutil.which("chromium-browser")


DRIVER = shutil.which("chromedriver")


def browser() -> Any:
    """A headless Chromium under Selenium, or skip saying what is missing."""
    try:
        from selenium import webdriver
        from selenium.webdriver.chrome.service import Service
    except ImportError:
        pytest.skip("selenium is not installed (the test extra installs it: pip install -e '.[test]')")
    if not CHROMIUM or not DRIVER:
        pytest.skip("headless Chromium is not installed: scripts/setup.sh installs Debian's chromium and "
                    "chromium-driver when run as root with apt-get (here it could not)")
    options = webdriver.ChromeOptions()
    for arg in ("--headless=new", "--no-sandbox", "--disable-dev-shm-usage", "--disable-gpu", "--window-size=1400,900",
                "--no-first-run", "--disable-extensions", "--disable-background-networking"):
        options.add_argument(arg)
    options.binary_location = CHROMIUM
    return webdriver.Chrome(service=Service(DRIVER), options=options)


def wait_for(driver: Any, condition: str, timeout: float = 120.0) -> Any:
    """Wait until the JavaScript expression ``condition`` is truthy; returns its value."""
    from selenium.webdriver.support.ui import WebDriverWait

    return WebDriverWait(driver, timeout, poll_frequency=0.05).until(lambda d: d.execute_script(f"return {condition}"))


def shown_metrics(driver: Any, method: str, names: list[str]) -> dict[str, float]:
    """The numbers the page shows for ``method`` (text of the metric cells, units stripped)."""
    out = {}
    for k in names:
        text = driver.find_element("id", f"metric-{method}-{k}").text
        out[k] = float(text.replace("dB", "").strip())
    return out


@pytest.fixture(scope="module")
def served(tmp_path_factory: pytest.TempPathFactory) -> Any:

    scene = load_builtin_scene("ar", SIZE, views=8, test_every=4, samples=1)
    model = load_builtin_backbone("ar")
    adapter = random_adapter(model, tmp_path_factory.mktemp("viewer-browser") / "controlgs.controlgs.safetensors")
    session = ViewerSession(model, scene.views("test"), {"controlgs": adapter}, name="browser test")
    server = make_server(session)
    threading.Thread(target=server.serve_forever, daemon=True).start()
    yield server, session
    server.shutdown()
    server.server_close()


def test_page_updates_and_shows_evaluate_grid_numbers(served: Any, tmp_path: Path) -> None:
    from selenium.webdriver.common.keys import Keys

    server, session = served
    driver = browser()
    try:
        driver.get(server.url)
        wait_for(driver, "window.viewer.generation >= 1 && document.getElementById('status').className === ''")
        first = driver.find_element("id", "img-controlgs-eye").get_attribute("src")
        assert first.startswith("data:image/png;base64,")
        generation = driver.execute_script("return window.viewer.generation")

        slider = driver.find_element("id", "downsample")
        for _ in range(6):  # six input events in a row: the older requests are superseded
            slider.send_keys(Keys.ARROW_RIGHT)
        target = float(slider.get_attribute("value"))
        state = wait_for(driver, f"window.viewer.generation > {generation} && window.viewer.last.downsample === {target}"
                                 " && document.getElementById('status').className === '' && window.viewer.last")
        wait_for(driver, "window.viewer.extra === window.viewer.generation")  # FLIP arrived
        assert state["downsample"] == pytest.approx(2.3) and state["power_saving"] == pytest.approx(0.4)
        assert driver.find_element("id", "img-controlgs-eye").get_attribute("src") != first
        assert driver.execute_script("return document.getElementById('img-controlgs-eye').complete")

        names = ["psnr", "ssim", *session.extra_metrics]
        grid = evaluate_grid(session.model, session.views, session.adapter_files, downsample=[state["downsample"]],
                             power_saving=[state["power_saving"]], optics_mode=state["optics"], ideal=False, progress=False)
        digits = {"psnr": 3, "ssim": 4, "flip": 4}
        for method in ("no_ss", "ss", "controlgs"):
            shown = shown_metrics(driver, method, names)
            for k in names:
                expected = float(grid.per_view[method][k][0, 0, state["view"]])
                assert shown[k] == pytest.approx(expected, abs=0.6 * 10 ** -digits.get(k, 4)), (method, k)
            exact = float(driver.find_element("id", f"metric-{method}-psnr").get_attribute("data-value"))
            assert exact == pytest.approx(float(grid.per_view[method]["psnr"][0, 0, state["view"]]), abs=1e-9)
        strengths = driver.find_element("id", "strengths").text
        assert "resample" in strengths and "lens" in strengths
        driver.save_screenshot(str(tmp_path / "viewer.png"))
        if os.environ.get("CONTROLGS_VIEWER_SCREENSHOT"):
            driver.save_screenshot(os.environ["CONTROLGS_VIEWER_SCREENSHOT"])
    finally:
        driver.quit()


pytestmark = pytest.mark.skipif(not (builtin_backbone_dir("ar") / "point_cloud").is_dir(),
                                reason="built-in backbone not baked")
