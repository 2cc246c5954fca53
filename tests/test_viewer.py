"""The viewer (``controlgs view``): state parsing, the session's renders and metrics, the HTTP
endpoints, path refusal and the cancellation of superseded requests."""

from __future__ import annotations

import base64
import http.client
import io
import json
import threading
import time
from typing import Any

import pytest
import torch

from controlgs_adapter import ControlGS
from controlgs_adapter.errors import InputValueError
from controlgs_adapter.evaluation import evaluate_grid
from controlgs_adapter.viewer import STAGES, Superseded, ViewerSession, ViewState, make_server, parse_state
from controlgs_adapter.viewer.server import Generations
from controlgs_adapter.viewer.session import orbit_camera, scene_centre

SIZE = 48


def random_adapter(model: Any, path: Any, seed: int = 0, **wrap: Any) -> Any:
    """An adapter with random conditions (ControlGS then differs from the SS-backbone); ``wrap``:
    :meth:`ControlGS.wrap`'s options."""
    cgs = ControlGS.wrap(model, **wrap)
    g = torch.Generator().manual_seed(seed)
    with torch.no_grad():
        cgs.injector.conditions.copy_(torch.randn(cgs.injector.conditions.shape, generator=g) * 0.5)
    cgs.save(path)
    cgs.unwrap()
    return path


@pytest.fixture(scope="module")
def scene() -> Any:
    from controlgs_adapter.scene import load_builtin_scene

    return load_builtin_scene("ar", SIZE, views=8, test_every=4, samples=1)


@pytest.fixture(scope="module")
def session(scene: Any, tmp_path_factory: pytest.TempPathFactory) -> ViewerSession:
    from controlgs_adapter.scene import load_builtin_backbone, render_planes

    model = load_builtin_backbone("ar")
    adapter = random_adapter(model, tmp_path_factory.mktemp("viewer") / "controlgs.controlgs.safetensors")
    return ViewerSession(model, scene.views("test"), {"controlgs": adapter}, name="test scene",
                         truth=lambda cam: render_planes(scene.planes, cam, samples=1)[0].float())


def decode(b64: str) -> torch.Tensor:
    from PIL import Image

    import numpy as np

    img = np.asarray(Image.open(io.BytesIO(base64.b64decode(b64))), dtype=np.float32)
    return torch.from_numpy(img).view(img.shape[0], img.shape[1], -1)


# ---------------------------------------------------------------- state parsing
def test_parse_state_defaults_and_values() -> None:
    assert parse_state({}, 2) == ViewState()
    s = parse_state({"view": 1, "azimuth": -30, "elevation": 12.5, "downsample": 3.7, "power_saving": 0.25,
                     "optics": "exact", "stages": ["optics", "lens"], "gaze": [0.5, -1]}, 2)
    assert (s.view, s.azimuth, s.elevation, s.downsample, s.power_saving, s.optics) == (1, -30.0, 12.5, 3.7, 0.25, "exact")
    assert s.stages == ("lens", "optics") and s.gaze == (0.5, -1.0) and s.orbit
    assert s.effects == {"lens": True, "resample": False, "display": False, "oled": False, "optics": True}
    assert s.runtime.downsample == 3.7 and s.runtime.gaze == (0.5, -1.0)


@pytest.mark.parametrize("data, message", [
    ({"downsample": 0.5}, "downsample must be a finite number in [1, 8]"),
    ({"downsample": 9}, "downsample must be a finite number in [1, 8]"),
    ({"downsample": "2"}, "downsample must be"),
    ({"downsample": True}, "downsample must be"),
    ({"downsample": float("nan")}, "downsample must be"),
    ({"power_saving": 0.9}, "power_saving must be a finite number in [0, 0.8]"),
    ({"azimuth": 200}, "azimuth must be"),
    ({"elevation": -90}, "elevation must be"),
    ({"view": 2}, "view must be an integer in [0, 1]"),
    ({"view": 0.5}, "view must be an integer"),
    ({"optics": "blur"}, "optics must be one of distortion, fast, exact"),
    ({"stages": "lens"}, "stages must be a list"),
    ({"stages": ["lens", "bloom"]}, "stages: unknown ['bloom']"),
    ({"gaze": [2, 0]}, "gaze x must be"),
    ({"gaze": [0]}, "gaze must be null or [x, y]"),
    ({"zoom": 2}, "unknown state field(s) ['zoom']"),
    ([1, 2], "the state must be a JSON object"),
])
def test_parse_state_refuses_bad_values(data: Any, message: str) -> None:
    with pytest.raises(InputValueError) as e:
        parse_state(data, 2)
    assert message in str(e.value)


# ---------------------------------------------------------------- orbit
def test_orbit_camera_turns_about_the_centre(scene: Any) -> None:
    cam = scene.test_cameras[0]
    centre = scene_centre(scene.test_cameras + scene.train_cameras, None)
    assert torch.allclose(centre, torch.tensor([0.0, 0.35, 0.0], dtype=torch.float64), atol=1e-4)  # the arc's target
    same = orbit_camera(cam, centre, 0.0, 0.0)
    assert torch.allclose(same.world_to_camera, cam.world_to_camera, atol=1e-6)
    up = -cam.world_to_camera[1, :3].double()
    for az, el in ((40.0, 0.0), (0.0, 30.0), (-120.0, -20.0)):
        moved = orbit_camera(cam, centre, az, el)
        c0, c1 = cam.center.double(), moved.center.double()
        assert abs(float((c1 - centre).norm() - (c0 - centre).norm())) < 1e-4          # same distance
        look = moved.to_camera(centre[None].float())[0]
        assert abs(float(look[0])) < 1e-3 and abs(float(look[1])) < 1e-3                # still looks at it
        if el:
            assert (float((c1 - c0) @ up) > 0) == (el > 0)                               # elevation > 0: up


# ---------------------------------------------------------------- the session
def test_render_matches_evaluate_grid(session: ViewerSession, scene: Any) -> None:
    state = parse_state({"view": 1, "downsample": 2.6, "power_saving": 0.3}, 2)
    out = session.render(state, tag=7)
    assert [m["name"] for m in out["methods"]] == ["no_ss", "ss", "controlgs"] and out["has_truth"]
    grid = evaluate_grid(session.model, session.views, session.adapter_files, downsample=[2.6], power_saving=[0.3],
                         ideal=False, progress=False)
    extra = session.extra(7)
    for m in out["methods"]:
        for k in ("psnr", "ssim"):
            assert m["metrics"][k] == pytest.approx(float(grid.per_view[m["name"]][k][0, 0, 1]), abs=1e-9)
        for k, v in extra[m["name"]].items():
            assert v == pytest.approx(float(grid.per_view[m["name"]][k][0, 0, 1]), abs=1e-9)
        assert decode(m["eye"]).shape == (SIZE, SIZE, 3) and decode(m["diff"]).shape == (SIZE, SIZE, 3)
    no_ss, _, cgs = out["methods"]
    assert decode(no_ss["rendered"]).shape == (round(SIZE / 2.6), round(SIZE / 2.6), 3)
    assert cgs["strengths"]["resample"] == pytest.approx(torch.log2(torch.tensor(2.6)).item() / 3, abs=1e-6)
    assert cgs["strengths"]["display"] == pytest.approx(0.3 / 0.8, abs=1e-6)
    assert 0.0 <= cgs["strengths"]["lens"]["min"] <= cgs["strengths"]["lens"]["mean"] <= cgs["strengths"]["lens"]["max"] <= 1
    overlay = decode(cgs["overlay"])
    assert overlay.shape == (SIZE, SIZE, 4) and overlay[..., 3].max() > 0
    with pytest.raises(Superseded):
        session.extra(6)


def test_state_independent_renders_are_cached(session: ViewerSession) -> None:
    session.render(parse_state({"downsample": 2.0}, 2))
    frames, small = len(session._frames), len(session._small)
    a = session.render(parse_state({"downsample": 2.01, "power_saving": 0.7}, 2))  # same display size, same view
    assert (len(session._frames), len(session._small)) == (frames, small)
    b = session.render(parse_state({"downsample": 2.01, "power_saving": 0.1}, 2))
    assert a["methods"][1]["rendered"] == b["methods"][1]["rendered"] and a["methods"][1]["eye"] != b["methods"][1]["eye"]


def test_stages_off_and_orbit(session: ViewerSession) -> None:
    out = session.render(parse_state({"stages": ["resample", "display"], "downsample": 3}, 2))
    assert out["methods"][1]["stages_run"] == ["resample", "display"]
    assert decode(out["methods"][1]["eye"]).shape == (SIZE, SIZE, 3)  # oled off: boxes at S for the metrics
    orbit = session.render(parse_state({"azimuth": 25, "elevation": 10}, 2))
    assert orbit["has_truth"] and orbit["methods"][0]["metrics"] is not None
    truth, session.truth = session.truth, None
    try:
        blind = session.render(parse_state({"azimuth": 26}, 2))
    finally:
        session.truth = truth
    assert not blind["has_truth"] and blind["gt"] is None and all(m["metrics"] is None for m in blind["methods"])


def test_check_drops_work_between_methods(session: ViewerSession) -> None:
    calls = []

    def check() -> None:
        calls.append(1)
        if len(calls) == 2:
            raise Superseded("newer")

    with pytest.raises(Superseded):
        session.render(parse_state({"downsample": 5.5}, 2), check)
    assert len(calls) == 2  # stopped after the first method


# ---------------------------------------------------------------- the server
@pytest.fixture(scope="module")
def server(session: ViewerSession) -> Any:
    srv = make_server(session)
    thread = threading.Thread(target=srv.serve_forever, daemon=True)
    thread.start()
    yield srv
    srv.shutdown()
    srv.server_close()


def request(srv: Any, method: str, path: str, body: Any = None, headers: dict[str, str] | None = None,
            raw: bytes | None = None) -> tuple[int, bytes]:
    conn = http.client.HTTPConnection(*srv.server_address[:2], timeout=60)
    data = raw if raw is not None else None if body is None else json.dumps(body).encode()
    conn.request(method, path, body=data, headers=headers or {})
    resp = conn.getresponse()
    out = resp.status, resp.read()
    conn.close()
    return out


def test_serves_page_and_static_files_only(server: Any) -> None:
    assert server.url.startswith("http://127.0.0.1:")
    status, body = request(server, "GET", "/")
    assert status == 200 and b"<title>ControlGS viewer</title>" in body
    for name in ("viewer.js", "viewer.css", "index.html"):
        assert request(server, "GET", f"/static/{name}")[0] == 200
    for path in ("/static/../session.py", "/static/%2e%2e/session.py", "/static/..%2fsession.py", "/etc/passwd",
                 "/static/", "/static/viewer.js/", "//etc/passwd", "/static/../../../../etc/passwd", "/api/render",
                 "/controlgs_adapter/viewer/session.py"):
        status, body = request(server, "GET", path)
        assert status == 404, path
        assert b"no such page" in body


def test_refuses_other_hosts_and_bad_bodies(server: Any) -> None:
    status, body = request(server, "GET", "/api/info", headers={"Host": "evil.example:80"})
    assert status == 403 and b"loopback" in body
    status, body = request(server, "POST", "/api/render", {"downsample": 12})
    assert status == 400 and "downsample must be a finite number in [1, 8]" in json.loads(body)["error"]
    status, body = request(server, "POST", "/api/render", raw=b"{not json", headers={"Content-Type": "application/json"})
    assert status == 400 and "not JSON" in json.loads(body)["error"]
    status, body = request(server, "POST", "/api/render", raw=b"x" * (65 * 1024))
    assert status == 400 and "at most" in json.loads(body)["error"]
    status, body = request(server, "POST", "/api/extra", {"generation": "1"})
    assert status == 400
    assert request(server, "POST", "/api/other", {})[0] == 404


def test_render_and_extra_endpoints(server: Any, session: ViewerSession) -> None:
    info = json.loads(request(server, "GET", "/api/info")[1])
    assert [m["name"] for m in info["methods"]] == ["no_ss", "ss", "controlgs"] and info["stages"] == list(STAGES)
    status, body = request(server, "POST", "/api/render", {"downsample": 4, "power_saving": 0.2})
    assert status == 200
    out = json.loads(body)
    g = out["generation"]
    assert out["state"]["downsample"] == 4.0 and len(out["methods"]) == 3
    status, body = request(server, "POST", "/api/extra", {"generation": g})
    assert status == 200 and set(json.loads(body)["metrics"]) == {"no_ss", "ss", "controlgs"}
    request(server, "POST", "/api/render", {"downsample": 4.5})
    assert request(server, "POST", "/api/extra", {"generation": g})[0] == 409  # stale


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


def test_generations() -> None:
    g = Generations()
    a = g.next()
    g.check(a)
    b = g.next()
    with pytest.raises(Superseded):
        g.check(a)
    g.check(b)


def test_loopback_only(session: ViewerSession) -> None:
    with pytest.raises(InputValueError, match="loopback"):
        make_server(session, host="0.0.0.0")


def test_cli_view_registered() -> None:
    from controlgs_adapter.cli import build_parser

    args = build_parser().parse_args(["view", "--port", "0", "--run", "somewhere"])
    assert args.command == "view" and args.port == 0 and args.run == "somewhere"


def test_cli_view_user_errors(tmp_path: Any, capsys: pytest.CaptureFixture[str]) -> None:
    from controlgs_adapter.cli import main

    assert main(["view", "--run", str(tmp_path / "nope")]) == 2
    assert "--run" in capsys.readouterr().err
    assert main(["view", "--run", str(tmp_path), "--test-views", "1"]) == 2
    assert "no controlgs.controlgs.safetensors" in capsys.readouterr().err
    assert main(["view", "--port", "70000"]) == 2
    assert "--port must be an integer in [0, 65535]" in capsys.readouterr().err


def test_cli_view_on_a_user_scene(tmp_path: Any, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]) -> None:
    """``controlgs view --run RUN`` on a COLMAP capture of non-square views and the built-in backbone's
    Scaffold-GS folder (model and data from RUN/run.json); the server's loop is replaced by two renders."""
    from _scene_writers import write_colmap
    from controlgs_adapter.backends import load_model_dir
    from controlgs_adapter.cli import main
    from controlgs_adapter.scene import builtin_backbone_dir, load_builtin_scene
    from controlgs_adapter.state import Camera
    from controlgs_adapter.viewer.server import ViewerServer

    scene = load_builtin_scene("ar", 32, views=8, test_every=8, samples=1)
    cams, images = [], []
    for c, img in zip(scene.test_cameras + scene.train_cameras, torch.cat([scene.test_images, scene.train_images])):
        k = c.intrinsics.clone()
        k[1, 2] -= 4
        cams.append(Camera(c.world_to_camera, k, 32, 24))
        images.append(img[:, 4:28].contiguous())
    data, run, model_dir = write_colmap(tmp_path / "colmap", cams, images), tmp_path / "run", builtin_backbone_dir("ar")
    run.mkdir()
    random_adapter(load_model_dir(model_dir), run / "controlgs.controlgs.safetensors")
    (run / "run.json").write_text(json.dumps({"model": str(model_dir), "data": str(data), "resolution": 32}))
    seen: list[dict[str, Any]] = []

    def two_renders(self: ViewerServer, poll_interval: float = 0.5) -> None:
        seen.append(self.session.render(parse_state({"downsample": 2.0}, len(self.session.cameras))))
        seen.append(self.session.render(parse_state({"azimuth": 15.0}, len(self.session.cameras))))

    monkeypatch.setattr(ViewerServer, "serve_forever", two_renders)
    assert main(["view", "--run", str(run), "--threads", "1"]) == 0
    out = capsys.readouterr().out
    assert "serving on http://127.0.0.1:" in out and "methods no_ss, ss, controlgs" in out
    dataset, orbit = seen
    assert dataset["size"] == [32, 24] and dataset["has_truth"] and dataset["methods"][2]["metrics"]["psnr"] > 10
    assert decode(dataset["methods"][2]["eye"]).shape == (24, 32, 3)
    assert not orbit["has_truth"] and orbit["methods"][2]["metrics"] is None  # your data: no ground truth off the views


def test_body_size_limit_and_loopback_host_names(server: Any) -> None:
    from controlgs_adapter.viewer.server import MAX_BODY

    body = json.dumps({"downsample": 12}).encode()
    padded = body[:-1] + b" " * (MAX_BODY - len(body)) + b"}"  # exactly MAX_BODY bytes: read, then refused on its value
    assert len(padded) == MAX_BODY
    status, out = request(server, "POST", "/api/render", raw=padded)
    assert status == 400 and "downsample must be" in json.loads(out)["error"]
    status, out = request(server, "POST", "/api/render", raw=padded + b" ")
    assert status == 400 and f"at most {MAX_BODY} bytes" in json.loads(out)["error"]
    port = server.server_address[1]
    for host in (f"[::1]:{port}", f"localhost:{port}", "127.0.0.1"):
        assert request(server, "GET", "/api/info", headers={"Host": host})[0] == 200, host
    for host in (f"[::2]:{port}", "127.0.0.2", "localhost.evil.example"):
        assert request(server, "GET", "/api/info", headers={"Host": host})[0] == 403, host
    for tag in (True, None, 1.0):
        status, out = request(server, "POST", "/api/extra", {"generation": tag})
        assert status == 400 and "/api/extra takes" in json.loads(out)["error"], tag


class FailingSession:
    """Stands in for a session whose render fails with a library bug (not a bad request)."""

    cameras = [None]

    def render(self, state: ViewState, check: Any, tag: int) -> dict[str, Any]:
        raise RuntimeError("boom")


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


def test_encode_png_rounds_to_the_nearest_level() -> None:
    from controlgs_adapter.viewer.session import encode_png

    img = torch.tensor([0.0, 0.5, 1.0, 1.5, -0.2, 0.3]).view(1, 2, 3).expand(3, 2, 3)  # values outside [0, 1] clip
    got = decode(encode_png(img))
    want = torch.tensor([0, 128, 255, 255, 0, 77], dtype=torch.float32).view(2, 3)  # round(v * 255)
    assert got.shape == (2, 3, 3) and torch.equal(got[..., 0], want) and torch.equal(got[..., 2], want)
    rgba = torch.cat([img, torch.full((1, 2, 3), 0.2)])
    assert torch.equal(decode(encode_png(rgba))[..., 3], torch.full((2, 3), 51.0))


def test_scene_centre_fallbacks_and_axes_by_hand() -> None:
    from controlgs_adapter.state import Camera

    k = torch.tensor([[10.0, 0.0, 8.0], [0.0, 10.0, 8.0], [0.0, 0.0, 1.0]])

    def looking_at_origin_from(c: list[float], sign: float = 1.0) -> Camera:  # sign -1: looking away from it
        z = -sign * torch.tensor(c, dtype=torch.float64)
        z = z / z.norm()
        x = torch.linalg.cross(torch.tensor([0.0, 1.0, 0.0], dtype=torch.float64), z)
        x = x / x.norm()
        r = torch.stack([x, torch.linalg.cross(z, x), z])
        w2c = torch.eye(4, dtype=torch.float64)
        w2c[:3, :3], w2c[:3, 3] = r, -(r @ torch.tensor(c, dtype=torch.float64))
        return Camera(w2c.float(), k, 16, 16)

    cams = [looking_at_origin_from([4.0, 0.0, 0.0]), looking_at_origin_from([0.0, 0.0, 4.0])]
    assert torch.allclose(scene_centre(cams, None), torch.zeros(3, dtype=torch.float64), atol=1e-5)
    points = torch.tensor([[0.0, 1.0, 2.0], [10.0, -1.0, 3.0], [2.0, 5.0, 9.0]])
    assert torch.equal(scene_centre(cams[:1], points), torch.tensor([2.0, 1.0, 3.0], dtype=torch.float64))  # median
    assert torch.equal(scene_centre(cams[:1], None), torch.zeros(3, dtype=torch.float64))
    away = [looking_at_origin_from([4.0, 0.0, 0.0], -1.0), looking_at_origin_from([0.0, 0.0, 4.0], -1.0)]
    # the axes meet at the origin, behind both cameras: the points' median is taken
    assert torch.equal(scene_centre(away, points), torch.tensor([2.0, 1.0, 3.0], dtype=torch.float64))


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
