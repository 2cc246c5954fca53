"""The viewer page in a real browser: headless Chromium (Debian's ``chromium`` + ``chromium-driver``,
installed by ``scripts/setup.sh`` when it runs as root with apt-get) driven through Selenium, which is
pointed at ``/usr/bin/chromedriver`` so that Selenium Manager downloads nothing. Skipped, saying why,
only where the browser is not installed."""

from __future__ import annotations

import os
import shutil
import threading
from pathlib import Path
from typing import Any

import pytest

from controlgs_adapter.evaluation import evaluate_grid
from controlgs_adapter.viewer import ViewerSession, make_server

from test_viewer import random_adapter

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
    from controlgs_adapter.scene import load_builtin_backbone, load_builtin_scene

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
