"""Tests of ``controlgs_adapter.viewer.server``: the page and static files, the JSON endpoints (render, extra,
info), loopback-only hosts, request bodies of any size or nesting (a 400 with one line, never a 500), superseded
requests, and errors that keep the server serving."""

from __future__ import annotations

import http.client
import json
import os
import shutil
import socket
import threading
import time
from pathlib import Path
from typing import Any, Iterator

import pytest
from helpers.adapters import random_adapter
from helpers.cli_runs import needs_backbone
from helpers.viewer_sessions import builtin_session

from controlgs_adapter.errors import InputValueError
from controlgs_adapter.evaluation import evaluate_grid
from controlgs_adapter.scene import load_builtin_backbone, load_builtin_scene
from controlgs_adapter.viewer import STAGES, Superseded, ViewerSession
from controlgs_adapter.viewer import server as vs_server
from controlgs_adapter.viewer.server import LOOPBACK, MAX_BODY, STATIC_FILES, Generations, ViewerServer, make_server
from controlgs_adapter.viewer.session import ViewState


@pytest.fixture(scope="module")
def live(tmp_path_factory: pytest.TempPathFactory) -> Any:
    """A session on the built-in scene with one adapter, "controlgs"."""
    session, _ = builtin_session(tmp_path_factory.mktemp("viewer"), {"controlgs": {}})
    return session


@pytest.fixture(scope="module")
def live_server(live: Any) -> Iterator[ViewerServer]:
    srv = make_server(live)
    threading.Thread(target=srv.serve_forever, daemon=True).start()
    yield srv
    srv.shutdown()
    srv.server_close()


@pytest.fixture()
def server() -> Iterator[ViewerServer]:
    """A server over a session that answers its parsed state."""
    srv = make_server(_EchoSession())  # type: ignore[arg-type]
    threading.Thread(target=srv.serve_forever, daemon=True).start()
    yield srv
    srv.shutdown()
    srv.server_close()


def request(srv: Any, method: str, path: str, body: Any = None, headers: dict[str, str] | None = None,
            raw: bytes | None = None) -> tuple[int, bytes]:
    """``(status, body bytes)`` of one request (``body`` sent as JSON, or ``raw`` bytes)."""
    conn = http.client.HTTPConnection(*srv.server_address[:2], timeout=60)
    data = raw if raw is not None else None if body is None else json.dumps(body).encode()
    conn.request(method, path, body=data, headers=headers or {})
    resp = conn.getresponse()
    out = resp.status, resp.read()
    conn.close()
    return out


def _ask(srv: Any, method: str, path: str, raw: bytes | None = None, host: str | None = None) -> tuple[int, Any]:
    """``(status, parsed JSON answer)``; ``host``: the Host header."""
    status, body = request(srv, method, path, raw=raw, headers={} if host is None else {"Host": host})
    return status, json.loads(body)


def _post(srv: ViewerServer, path: str, raw: bytes) -> tuple[int, dict[str, Any]]:
    status, body = request(srv, "POST", path, raw=raw, headers={"Content-Type": "application/json"})
    return status, json.loads(body)


def _one_line_400(status: int, body: dict[str, Any], *words: str) -> None:
    assert status == 400, body
    assert set(body) == {"error"} and "\n" not in body["error"] and len(body["error"]) < 300
    for w in words:
        assert w in body["error"]


class _EchoSession:
    """Stands in for a session: one view, a render that returns the parsed state."""

    cameras = [None]

    def render(self, state: ViewState, check: Any, tag: int) -> dict[str, Any]:
        return {"state": state.to_json()}


class _StubSession:
    """Stands in for a session (the server's part is under test): a render answers ``self.answer`` and
    records the worker thread's name; ``extra`` answers one metric."""

    cameras = [None, None]

    def __init__(self, answer: Any) -> None:
        self.answer, self.threads = answer, []  # type: ignore[var-annotated]

    def info(self) -> dict[str, Any]:
        return {"name": "stub"}

    def render(self, state: ViewState, check: Any, tag: int) -> dict[str, Any]:
        self.threads.append(threading.current_thread().name)
        return dict(self.answer)

    def extra(self, tag: int, check: Any) -> dict[str, Any]:
        return {"ss": {"flip": 0.5}}


class GatedSession:
    """Stands in for a session: a render takes 3 steps with a check after each; every step waits for
    ``gate`` (opened by the test), so which request runs when does not depend on timing."""

    cameras = [None]

    def __init__(self) -> None:
        self.gate, self.running = threading.Event(), threading.Event()
        self.steps: list[tuple[int, int]] = []

    def render(self, state: ViewState, check: Any, tag: int) -> dict[str, Any]:
        self.running.set()
        for i in range(3):
            assert self.gate.wait(30), "the test never opened the gate"
            self.steps.append((tag, i))
            check()
        return {"state": state.to_json()}


class FailingSession:
    """Stands in for a session whose render fails with a library bug (not a bad request)."""

    cameras = [None]

    def render(self, state: ViewState, check: Any, tag: int) -> dict[str, Any]:
        raise RuntimeError("boom")


# ----------------------------------------------------------------------------- pages, endpoints and headers

def test_serves_page_and_static_files_only(live_server: Any) -> None:
    assert live_server.url.startswith("http://127.0.0.1:")
    status, body = request(live_server, "GET", "/")
    assert status == 200 and b"<title>ControlGS viewer</title>" in body
    for name in ("viewer.js", "viewer.css", "index.html"):
        assert request(live_server, "GET", f"/static/{name}")[0] == 200
    for path in ("/static/../session.py", "/static/%2e%2e/session.py", "/static/..%2fsession.py", "/etc/passwd",
                 "/static/", "/static/viewer.js/", "//etc/passwd", "/static/../../../../etc/passwd", "/api/render",
                 "/controlgs_adapter/viewer/session.py"):
        status, body = request(live_server, "GET", path)
        assert status == 404, path
        assert b"no such page" in body


def test_server_headers_and_query_strings(live: Any) -> None:
    srv = make_server(live)
    threading.Thread(target=srv.serve_forever, daemon=True).start()
    try:
        assert LOOPBACK == ("127.0.0.1", "localhost", "[::1]") and MAX_BODY == 65536
        for name, ctype in (("index.html", "text/html"), ("viewer.js", "text/javascript"), ("viewer.css", "text/css")):
            conn = http.client.HTTPConnection(*srv.server_address[:2], timeout=60)
            conn.request("GET", f"/static/{name}?v=3")  # a query string is ignored
            resp = conn.getresponse()
            body = resp.read()
            conn.close()
            assert resp.status == 200 and resp.getheader("Content-Type") == f"{ctype}; charset=utf-8" == STATIC_FILES[name]
            assert resp.getheader("Cache-Control") == "no-store" and resp.getheader("X-Content-Type-Options") == "nosniff"
            assert int(resp.getheader("Content-Length")) == len(body) == len(srv.static[name])
        conn = http.client.HTTPConnection(*srv.server_address[:2], timeout=60)
        conn.request("GET", "/api/info?x=1")
        resp = conn.getresponse()
        assert resp.status == 200 and resp.getheader("Content-Type") == "application/json"
        assert json.loads(resp.read())["name"] == "tiny"
        conn.close()
        conn = http.client.HTTPConnection(*srv.server_address[:2], timeout=60)
        conn.request("POST", "/api/render?x=1", body=json.dumps({"downsample": 9}).encode())
        resp = conn.getresponse()
        assert resp.status == 400 and "downsample must be" in json.loads(resp.read())["error"]
        conn.close()
        conn = http.client.HTTPConnection(*srv.server_address[:2], timeout=60)
        conn.request("POST", "/api/extra", body=b"[1]")  # JSON, but not an object
        resp = conn.getresponse()
        assert resp.status == 400 and "/api/extra takes" in json.loads(resp.read())["error"]
        conn.close()
        conn = http.client.HTTPConnection(*srv.server_address[:2], timeout=60)
        conn.request("POST", "/api/render", body=b"\xff\xfe")  # not UTF-8
        resp = conn.getresponse()
        assert resp.status == 400 and "not JSON" in json.loads(resp.read())["error"]
        conn.close()
        assert srv.url == f"http://127.0.0.1:{srv.server_address[1]}/"
    finally:
        srv.shutdown()
        srv.server_close()
    local = make_server(live, host="localhost")
    try:
        assert local.server_address[1] > 0
    finally:
        local.server_close()


def test_render_and_extra_endpoints(live_server: Any) -> None:
    info = json.loads(request(live_server, "GET", "/api/info")[1])
    assert [m["name"] for m in info["methods"]] == ["no_ss", "ss", "controlgs"] and info["stages"] == list(STAGES)
    status, body = request(live_server, "POST", "/api/render", {"downsample": 4, "power_saving": 0.2})
    assert status == 200
    out = json.loads(body)
    g = out["generation"]
    assert out["state"]["downsample"] == 4.0 and len(out["methods"]) == 3
    status, body = request(live_server, "POST", "/api/extra", {"generation": g})
    assert status == 200 and set(json.loads(body)["metrics"]) == {"no_ss", "ss", "controlgs"}
    request(live_server, "POST", "/api/render", {"downsample": 4.5})
    assert request(live_server, "POST", "/api/extra", {"generation": g})[0] == 409  # stale


def test_server_answers_with_stub_session() -> None:
    stub = _StubSession({"x": 1.5})
    srv = make_server(stub)  # type: ignore[arg-type]
    threading.Thread(target=srv.serve_forever, daemon=True).start()
    try:
        port = srv.server_address[1]
        assert port >= 1024  # the default port 0: a free ephemeral one
        assert _ask(srv, "POST", "/api/render", b"{}") == (200, {"x": 1.5, "generation": 1})
        assert _ask(srv, "POST", "/api/render", b'{"view": 1}') == (200, {"x": 1.5, "generation": 2})
        assert all(name.startswith("controlgs-view") for name in stub.threads) and len(stub.threads) == 2
        # a one-byte body is read (the lower bound is 1 byte), then refused as not an object
        status, out = _ask(srv, "POST", "/api/render", b"1")
        assert status == 400 and out["error"].startswith("the state must be a JSON object")
        assert _ask(srv, "POST", "/api/extra", b'{"generation": 2}') == (200, {"generation": 2, "metrics": {"ss": {"flip": 0.5}}})
        assert _ask(srv, "POST", "/api/extra", b'{"generation": 1}') == (
            409, {"superseded": True, "error": "request 1 was superseded by 2"})
        # the host check: a bare IPv6 loopback (no port) is loopback too; a port on another host is not
        assert _ask(srv, "GET", "/api/info", host="[::1]") == (200, {"name": "stub"})
        assert _ask(srv, "GET", "/api/info", host=f"localhost:{port}") == (200, {"name": "stub"})
        status, out = _ask(srv, "GET", "/api/info", host=f"example.com:{port}")
        assert status == 403 and out["error"] == "host 'example.com' refused: the viewer answers loopback addresses only"
        status, out = _ask(srv, "POST", "/api/render", b"{}", host="127.0.0.1.evil:80")
        assert status == 403 and stub.threads == ["controlgs-view_0"] * 2  # refused before any work
        status, out = _ask(srv, "GET", "/nope?x=1")
        assert status == 404 and out["error"] == "no such page: '/nope' (the viewer serves only / and its static files)"
        status, out = _ask(srv, "POST", "/api/nope", b"{}")
        assert status == 404 and out["error"] == "no such endpoint: '/api/nope'"
        # a result that is not JSON (a NaN) is a server error with its reason, and the server keeps serving
        stub.answer = {"x": float("nan")}
        status, out = _ask(srv, "POST", "/api/render", b"{}")
        assert status == 500 and out["error"].startswith("ValueError: Out of range float values are not JSON compliant")
        stub.answer = {"x": 2}
        assert _ask(srv, "POST", "/api/render", b"{}")[0] == 200
    finally:
        srv.shutdown()
        srv.server_close()
    direct = vs_server.ViewerServer(stub)  # type: ignore[arg-type]
    try:
        assert direct.server_address[1] >= 1024 and direct.url.startswith("http://127.0.0.1:")
    finally:
        direct.server_close()


# ----------------------------------------------------------------------------- hosts and bodies

def test_loopback_only(live: Any) -> None:
    with pytest.raises(InputValueError, match="loopback"):
        make_server(live, host="0.0.0.0")


def test_a_refused_host_gets_the_403_and_nothing_else(live: Any) -> None:
    """A request for another host name is answered 403 and not handled (server._host_ok: DNS rebinding):
    everything the server writes on that connection up to its close is the one 403 answer (a handled
    request would follow it with a second answer, here the scene's info)."""
    srv = make_server(live)
    threading.Thread(target=srv.serve_forever, daemon=True).start()
    try:
        with socket.create_connection(srv.server_address[:2], timeout=60) as sock:
            sock.sendall(b"GET /api/info HTTP/1.1\r\nHost: evil.example\r\nConnection: close\r\n\r\n")
            data = b""
            while chunk := sock.recv(65536):
                data += chunk
    finally:
        srv.shutdown()
        srv.server_close()
    head, _, body = data.partition(b"\r\n\r\n")
    assert head.startswith(b"HTTP/1.1 403 ") and data.count(b"HTTP/1.1 ") == 1, data
    assert json.loads(body) == {"error": "host 'evil.example' refused: the viewer answers loopback addresses only"}


def test_other_hosts_and_bad_bodies_are_refused(live_server: Any) -> None:
    """Only loopback host names are served (403 otherwise); a body is read up to MAX_BODY bytes, then refused on
    its value (400 naming the field), a longer one or one that is not JSON is a 400."""
    status, body = request(live_server, "GET", "/api/info", headers={"Host": "evil.example:80"})
    assert status == 403 and b"loopback" in body
    status, body = request(live_server, "POST", "/api/render", {"downsample": 12})
    assert status == 400 and json.loads(body)["error"].startswith("downsample ") and "got 12" in json.loads(body)["error"]
    status, body = request(live_server, "POST", "/api/render", raw=b"{not json", headers={"Content-Type": "application/json"})
    assert status == 400 and "not JSON" in json.loads(body)["error"]
    status, body = request(live_server, "POST", "/api/render", raw=b"x" * (65 * 1024))
    assert status == 400 and "at most" in json.loads(body)["error"]
    assert request(live_server, "POST", "/api/other", {})[0] == 404
    body = json.dumps({"downsample": 12}).encode()
    padded = body[:-1] + b" " * (MAX_BODY - len(body)) + b"}"  # exactly MAX_BODY bytes: read, then refused on its value
    assert len(padded) == MAX_BODY
    status, out = request(live_server, "POST", "/api/render", raw=padded)
    assert status == 400 and "downsample must be" in json.loads(out)["error"]
    status, out = request(live_server, "POST", "/api/render", raw=padded + b" ")
    assert status == 400 and f"at most {MAX_BODY} bytes" in json.loads(out)["error"]
    port = live_server.server_address[1]
    for host in (f"[::1]:{port}", f"localhost:{port}", "127.0.0.1"):
        assert request(live_server, "GET", "/api/info", headers={"Host": host})[0] == 200, host
    for host in (f"[::2]:{port}", "127.0.0.2", "localhost.evil.example"):
        assert request(live_server, "GET", "/api/info", headers={"Host": host})[0] == 403, host
    for tag in (True, None, 1.0, "1"):
        status, out = request(live_server, "POST", "/api/extra", {"generation": tag})
        assert status == 400 and "/api/extra takes" in json.loads(out)["error"], tag


@pytest.mark.parametrize("field", ["view", "downsample", "power_saving", "azimuth", "elevation"])
def test_a_number_of_any_size_is_a_400(server: ViewerServer, field: str) -> None:
    for literal in ("1" + "0" * 400, "-" + "9" * 400, "1e400", "NaN", "-Infinity"):
        _one_line_400(*_post(server, "/api/render", f'{{"{field}": {literal}}}'.encode()), f"{field} must be")
    ok = {"view": 0, "downsample": 3, "power_saving": 0.5, "azimuth": 10, "elevation": -10}[field]
    status, body = _post(server, "/api/render", f'{{"{field}": {ok}}}'.encode())
    assert status == 200 and body["state"][field] == ok


def test_a_number_past_the_interpreter_digit_limit_is_a_400(server: ViewerServer) -> None:
    _one_line_400(*_post(server, "/api/render", b'{"downsample": 1' + b"0" * 5000 + b"}"), "not JSON")
    _one_line_400(*_post(server, "/api/extra", b'{"generation": 1' + b"0" * 5000 + b"}"), "not JSON")


@pytest.mark.parametrize("open_, close", [(b"[", b"]"), (b'{"a":', b"}")])
@pytest.mark.parametrize("path", ["/api/render", "/api/extra"])
def test_json_of_any_nesting_is_a_400(server: ViewerServer, path: str, open_: bytes, close: bytes) -> None:
    depth = (MAX_BODY - 10) // (len(open_) + len(close))
    _one_line_400(*_post(server, path, open_ * depth + b"1" + close * depth), "nested too deeply")
    depth = 400  # within the parser's reach: refused by the state's checks, the message kept short
    body = b'{"gaze": ' + b"[" * depth + b"1" + b"]" * depth + b"}"
    _one_line_400(*_post(server, path, body), "gaze" if path == "/api/render" else "/api/extra takes")
    status, _ = _post(server, "/api/render", b"{}")
    assert status == 200  # still serving


# ----------------------------------------------------------------------------- superseded requests and errors

def test_generations() -> None:
    g = Generations()
    a = g.next()
    g.check(a)
    b = g.next()
    with pytest.raises(Superseded):
        g.check(a)
    g.check(b)


def test_newer_request_supersedes_older_ones() -> None:
    slow = GatedSession()
    srv = make_server(slow)  # type: ignore[arg-type]
    threading.Thread(target=srv.serve_forever, daemon=True).start()
    try:
        results: dict[int, tuple[int, bytes]] = {}

        def send(i: int, d: float) -> None:
            results[i] = request(srv, "POST", "/api/render", {"downsample": d})

        def start(i: int) -> None:  # request i is in: it holds generation i + 1
            threads[i].start()
            deadline = time.monotonic() + 30
            while srv.generations.current < i + 1:
                assert time.monotonic() < deadline, f"request {i} never reached the server"
                time.sleep(0.005)

        threads = [threading.Thread(target=send, args=(i, 1.0 + i)) for i in range(3)]
        start(0)
        assert slow.running.wait(30)       # the first one runs (held before its first step),
        start(1)                           # the second one is queued behind it
        start(2)                           # and superseded by the third before it starts
        slow.gate.set()
        for t in threads:
            t.join(30)
        assert results[0][0] == 409 and results[1][0] == 409 and results[2][0] == 200
        assert json.loads(results[2][1])["state"]["downsample"] == 3.0
        assert slow.steps == [(1, 0), (3, 0), (3, 1), (3, 2)]  # 1 dropped mid-way, 2 never ran, 3 ran through
    finally:
        slow.gate.set()
        srv.shutdown()
        srv.server_close()


def test_server_errors_keep_it_serving() -> None:
    srv = make_server(FailingSession())  # type: ignore[arg-type]
    threading.Thread(target=srv.serve_forever, daemon=True).start()
    try:
        status, out = request(srv, "POST", "/api/render", {})
        assert status == 500 and json.loads(out) == {"error": "RuntimeError: boom"}
        status, out = request(srv, "POST", "/api/render", raw=b"{}", headers={"Content-Length": "two"})
        assert status == 400 and json.loads(out)["error"] == "bad Content-Length"
        status, out = request(srv, "POST", "/api/render", raw=b"")
        assert status == 400 and "at most" in json.loads(out)["error"]
        status, out = request(srv, "POST", "/api/render", {"view": 1})  # one camera: views are [0, 0]
        assert status == 400 and "view must be an integer in [0, 0]" in json.loads(out)["error"]
        assert request(srv, "GET", "/")[0] == 200
    finally:
        srv.shutdown()
        srv.server_close()


def test_a_client_that_hangs_up_is_not_reported_but_other_errors_are(capsys) -> None:
    srv = make_server(FailingSession())  # type: ignore[arg-type]
    try:
        for exc, reported in ((BrokenPipeError(32, "Broken pipe"), False), (ConnectionResetError(104, "reset"), False),
                              (ValueError("a real bug"), True)):
            try:
                raise exc
            except Exception:
                srv.handle_error(None, ("127.0.0.1", 1))
            err = capsys.readouterr().err
            assert ("Traceback" in err and type(exc).__name__ in err) if reported else err == "", (exc, err)
    finally:
        srv.server_close()


# ----------------------------------------------------------------------------- the page in a browser

#: the headless browser the page test drives (Debian's chromium and chromium-driver)
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
    """A 64 px session with one adapter, served."""
    scene = load_builtin_scene("ar", 64, views=8, test_every=4, samples=1)
    model = load_builtin_backbone("ar")
    adapter = random_adapter(model, tmp_path_factory.mktemp("viewer-browser") / "controlgs.controlgs.safetensors")
    session = ViewerSession(model, scene.views("test"), {"controlgs": adapter}, name="browser test")
    server = make_server(session)
    threading.Thread(target=server.serve_forever, daemon=True).start()
    yield server, session
    server.shutdown()
    server.server_close()


@needs_backbone
def test_page_updates_and_shows_evaluate_grid_numbers(served: Any, tmp_path: Path) -> None:
    """In headless Chromium: six slider moves in a row supersede the older requests, the page shows the last
    state's images and the numbers evaluate_grid computes for it, and the strengths."""
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
