"""The viewer's pieces pinned by number (issue 15 section 5): the state's defaults, bounds and
refusals, the orbit's directions by hand, the scene centre's fallbacks, the heat overlay's pixels,
the caches, the shared copy, the session's info / strengths / difference images / extra metrics,
and the server's headers."""

from __future__ import annotations

import base64
import http.client
import io
import json
import math
import threading
from typing import Any

import pytest
import torch

from controlgs_adapter.errors import InputValueError
from controlgs_adapter.state import Camera
from controlgs_adapter.viewer import STAGES, OPTICS_MODES, ViewerSession, ViewState, make_server, parse_state
from controlgs_adapter.viewer import server as vs_server
from controlgs_adapter.viewer import session as vs
from controlgs_adapter.viewer.server import LOOPBACK, MAX_BODY, STATIC_FILES
from controlgs_adapter.viewer.session import _Cache, _shared_copy, heat_overlay, orbit_camera, scene_centre
from test_viewer import random_adapter

SIZE = 16


def _decode(b64: str) -> torch.Tensor:
    """base64 PNG -> float ``[H, W, C]`` in 0..255."""
    import numpy as np
    from PIL import Image

    img = np.asarray(Image.open(io.BytesIO(base64.b64decode(b64))), dtype=np.float32)
    return torch.from_numpy(img).view(img.shape[0], img.shape[1], -1)


# ---------------------------------------------------------------- parse_state
def test_view_state_defaults_and_constants() -> None:
    d = parse_state({}, 3)
    assert (d.view, d.azimuth, d.elevation, d.downsample, d.power_saving, d.optics, d.stages, d.gaze) == (
        0, 0.0, 0.0, 2.0, 0.4, "fast", STAGES, None)
    assert STAGES == ("lens", "resample", "display", "oled", "optics") and OPTICS_MODES == ("distortion", "fast", "exact")
    assert (vs.DOWNSAMPLE_RANGE, vs.POWER_SAVING_RANGE, vs.AZIMUTH_RANGE, vs.ELEVATION_RANGE, vs.DIFF_GAIN) == (
        (1.0, 8.0), (0.0, 0.8), (-180.0, 180.0), (-80.0, 80.0), 2.0)
    assert d.to_json() == {"view": 0, "azimuth": 0.0, "elevation": 0.0, "downsample": 2.0, "power_saving": 0.4,
                           "optics": "fast", "stages": list(STAGES), "gaze": None}
    assert not d.orbit and d.effects == {s: True for s in STAGES}
    r = d.runtime
    assert (r.downsample, r.power_saving, r.gaze) == (2.0, 0.4, None)


def test_view_state_orbit_and_json() -> None:
    assert ViewState(azimuth=0.0, elevation=-5.0).orbit and ViewState(azimuth=3.0).orbit
    s = ViewState(stages=("lens",), gaze=(0.25, -0.5))
    assert s.to_json()["gaze"] == [0.25, -0.5] and s.to_json()["stages"] == ["lens"]
    assert json.dumps(s.to_json())  # JSON-ready: lists, not tuples only
    assert s.effects == {"lens": True, "resample": False, "display": False, "oled": False, "optics": False}
    assert s.runtime.gaze == (0.25, -0.5)


def test_parse_state_accepts_the_bounds() -> None:
    lo = parse_state({"view": 0, "azimuth": -180, "elevation": -80, "downsample": 1, "power_saving": 0,
                      "gaze": [-1, -1]}, 3)
    hi = parse_state({"view": 2, "azimuth": 180, "elevation": 80, "downsample": 8, "power_saving": 0.8,
                      "gaze": [1, 1]}, 3)
    assert (lo.view, lo.azimuth, lo.elevation, lo.downsample, lo.power_saving, lo.gaze) == (0, -180.0, -80.0, 1.0, 0.0, (-1.0, -1.0))
    assert (hi.view, hi.azimuth, hi.elevation, hi.downsample, hi.power_saving, hi.gaze) == (2, 180.0, 80.0, 8.0, 0.8, (1.0, 1.0))
    assert isinstance(hi.view, int) and not isinstance(hi.view, bool)
    # stages: any order, duplicates: kept once, in pipeline order; an empty list switches everything off
    assert parse_state({"stages": ["optics", "lens", "optics"]}, 1).stages == ("lens", "optics")
    assert parse_state({"stages": []}, 1).stages == ()
    for optics in OPTICS_MODES:
        assert parse_state({"optics": optics}, 1).optics == optics


@pytest.mark.parametrize("data, message", [
    ({"view": -1}, "view must be an integer in [0, 2]"),
    ({"view": 3}, "view must be an integer in [0, 2]"),
    ({"azimuth": -180.5}, "azimuth must be a finite number in [-180, 180]"),
    ({"elevation": 80.5}, "elevation must be a finite number in [-80, 80]"),
    ({"power_saving": -0.1}, "power_saving must be a finite number in [0, 0.8]"),
    ({"downsample": 8.01}, "downsample must be a finite number in [1, 8]"),
    ({"stages": ["lens", 3]}, "stages must be a list of stage names among lens, resample, display, oled, optics"),
    ({"stages": ("lens",)}, "stages must be a list"),
    ({"gaze": "ab"}, "gaze must be null or [x, y] in [-1, 1]"),
    ({"gaze": [0, 0, 0]}, "gaze must be null or [x, y]"),
    ({"gaze": [0, 1.5]}, "gaze y must be a finite number in [-1, 1]"),
    ({"gaze": [-1.5, 0]}, "gaze x must be"),
    ({"b": 1, "a": 2, "view": 0}, "unknown state field(s) ['a', 'b']; fields: view, azimuth, elevation, downsample, "
                                  "power_saving, optics, stages, gaze"),
    ({"optics": None}, "optics must be one of distortion, fast, exact, got None"),
    ("view", "the state must be a JSON object with fields view, azimuth, elevation, downsample, power_saving, optics, "
             "stages, gaze, got str"),
])
def test_parse_state_refusals(data: Any, message: str) -> None:
    with pytest.raises(InputValueError) as e:
        parse_state(data, 3)
    assert message in str(e.value)


# ---------------------------------------------------------------- orbit and centre
def _cam_at_minus_z(dist: float = 4.0) -> Camera:
    """Identity rotation (OpenCV: x right, y down, z forward) at world (0, 0, -dist): looks at the origin."""
    w2c = torch.eye(4)
    w2c[2, 3] = dist
    k = torch.tensor([[8.0, 0.0, 4.0], [0.0, 8.0, 4.0], [0.0, 0.0, 1.0]])
    return Camera(w2c, k, 8, 8)


def test_orbit_camera_directions_by_hand() -> None:
    cam, o = _cam_at_minus_z(), torch.zeros(3, dtype=torch.float64)
    # azimuth 90 about the up axis -y (right-handed): (0, 0, -4) -> (4, 0, 0), to the scene's right (+x);
    # the camera keeps its up row (0, 1, 0) and now looks along -x; x row = y row cross z row = (0, 0, 1)
    right = orbit_camera(cam, o, 90.0, 0.0)
    assert torch.allclose(right.center.double(), torch.tensor([4.0, 0.0, 0.0], dtype=torch.float64), atol=1e-5)
    want = torch.tensor([[0.0, 0.0, 1.0, 0.0], [0.0, 1.0, 0.0, 0.0], [-1.0, 0.0, 0.0, 4.0], [0.0, 0.0, 0.0, 1.0]])
    assert torch.allclose(right.world_to_camera, want, atol=1e-6)
    assert right.world_to_camera.dtype == cam.world_to_camera.dtype
    assert (right.width, right.height) == (8, 8) and torch.equal(right.intrinsics, cam.intrinsics)
    # elevation 90: up, i.e. to world -y (OpenCV y points down): (0, -4, 0), looking along +y
    up = orbit_camera(cam, o, 0.0, 90.0)
    assert torch.allclose(up.center.double(), torch.tensor([0.0, -4.0, 0.0], dtype=torch.float64), atol=1e-5)
    assert torch.allclose(up.world_to_camera[2, :3], torch.tensor([0.0, 1.0, 0.0]), atol=1e-6)
    assert torch.allclose(up.world_to_camera[0, :3], torch.tensor([1.0, 0.0, 0.0]), atol=1e-6)  # right unchanged
    # about another centre: the camera turns about it, not about the origin
    c = torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64)  # 5 in front of the camera
    moved = orbit_camera(cam, c, -90.0, 0.0)  # to the left: (-5, 0, 1)
    assert torch.allclose(moved.center.double(), torch.tensor([-5.0, 0.0, 1.0], dtype=torch.float64), atol=1e-5)
    # azimuth then elevation: 90 right then 90 up from (0, 0, -4) ends above the centre
    both = orbit_camera(cam, o, 90.0, 90.0)
    assert torch.allclose(both.center.double(), torch.tensor([0.0, -4.0, 0.0], dtype=torch.float64), atol=1e-5)


def test_rotation_rodrigues_by_hand() -> None:
    r = vs._rotation(torch.tensor([0.0, 0.0, 2.0], dtype=torch.float64), 90.0)  # axis normalised
    want = torch.tensor([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]], dtype=torch.float64)
    assert torch.allclose(r, want, atol=1e-12)
    r30 = vs._rotation(torch.tensor([1.0, 0.0, 0.0], dtype=torch.float64), 30.0)
    c, s = 3**0.5 / 2, 0.5
    assert torch.allclose(r30, torch.tensor([[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]], dtype=torch.float64), atol=1e-12)


def test_scene_centre_parallel_axes_and_one_camera_fall_back() -> None:
    k = torch.tensor([[8.0, 0.0, 4.0], [0.0, 8.0, 4.0], [0.0, 0.0, 1.0]])

    def at(x: float) -> Camera:  # looking along +z from (x, 0, -4)
        w2c = torch.eye(4)
        w2c[0, 3], w2c[2, 3] = -x, 4.0
        return Camera(w2c, k, 8, 8)

    points = torch.tensor([[1.0, 2.0, 3.0], [3.0, 0.0, 5.0], [2.0, 1.0, 4.0]])
    median = torch.tensor([2.0, 1.0, 4.0], dtype=torch.float64)
    assert torch.equal(scene_centre([at(0.0), at(2.0)], points), median)  # parallel axes: singular, the median
    assert torch.equal(scene_centre([at(0.0)], points), median)  # one camera: no intersection
    assert torch.equal(scene_centre([at(0.0), at(2.0)], points[:0]), torch.zeros(3, dtype=torch.float64))  # no points
    # two converging cameras: (0, 0, -4) looking +z and (4, 0, 0) looking -x meet at the origin
    w2c = torch.tensor([[0.0, 0.0, 1.0, 0.0], [0.0, 1.0, 0.0, 0.0], [-1.0, 0.0, 0.0, 4.0], [0.0, 0.0, 0.0, 1.0]])
    got = scene_centre([_cam_at_minus_z(), Camera(w2c, k, 8, 8)], points)
    assert torch.allclose(got, torch.zeros(3, dtype=torch.float64), atol=1e-6)


# ---------------------------------------------------------------- heat overlay
def _pixel_point(cam: Camera, px: float, py: float, z: float = 1.0) -> list[float]:
    """World point seen at pixel centre (px + 0.5, py + 0.5) by an identity camera (fx = fy = 8)."""
    k = cam.intrinsics
    return [(px + 0.5 - float(k[0, 2])) / float(k[0, 0]) * z, (py + 0.5 - float(k[1, 2])) / float(k[1, 1]) * z, z]


def test_heat_overlay_pixels_by_hand() -> None:
    cam = Camera(torch.eye(4), torch.tensor([[8.0, 0.0, 4.0], [0.0, 8.0, 4.0], [0.0, 0.0, 1.0]]), 8, 8)
    # k = 2 max(1, round(8 / 48)) + 1 = 3: each anchor spreads over its 3x3 neighbourhood
    pos = torch.tensor([_pixel_point(cam, 2, 5), _pixel_point(cam, 6, 0), _pixel_point(cam, 2, 1), _pixel_point(cam, 2, 1),
                        [0.0, 0.0, -1.0],                                 # behind the camera
                        _pixel_point(cam, 9, 2),                          # right of the image
                        _pixel_point(cam, -1, 2),                         # left of it
                        _pixel_point(cam, 5, 5)])                         # a non-finite strength
    strength = torch.tensor([0.5, 1.0, 0.2, 0.6, 1.0, 1.0, 1.0, float("nan")])
    out = heat_overlay(pos, strength, cam)
    assert out.shape == (4, 8, 8)
    # the map's colours: black-blue (0, 0, 0.2), purple (0.45, 0.05, 0.55), orange (0.9, 0.35, 0.1), yellow (1, 0.95, 0.3)
    # lam 0.5 -> t = 1.5: halfway between purple and orange; lam 1: yellow; two anchors in a pixel: the mean 0.4
    # -> t = 1.2: purple + 0.2 (orange - purple)
    cases = (((2, 5), [0.675, 0.2, 0.325]), ((6, 0), [1.0, 0.95, 0.3]), ((2, 1), [0.54, 0.11, 0.46]))
    for (x, y), colour in ((xy, torch.tensor(c)) for xy, c in cases):
        for dx in (-1, 0, 1):
            for dy in (-1, 0, 1):
                if 0 <= x + dx < 8 and 0 <= y + dy < 8:
                    assert torch.allclose(out[:3, y + dy, x + dx], colour, atol=1e-6), (x + dx, y + dy)
                    assert out[3, y + dy, x + dx] == pytest.approx(0.55)
    covered = torch.zeros(8, 8, dtype=torch.bool)
    covered[4:7, 1:4] = covered[0:2, 5:8] = covered[0:3, 1:4] = True
    assert torch.equal(out[3] > 0, covered)  # nothing from the culled anchors
    assert torch.allclose(out[:3, ~covered], torch.tensor([[0.0], [0.0], [0.2]]), atol=1e-7)  # lam 0: the first colour


def test_heat_overlay_window_grows_with_the_image() -> None:
    for size, half in ((72, 2), (96, 2), (8, 1), (144, 3)):  # k = 2 max(1, round(size / 48)) + 1; 72 / 48 = 1.5 -> 2
        cam = Camera(torch.eye(4), torch.tensor([[8.0, 0.0, size / 2], [0.0, 8.0, size / 2], [0.0, 0.0, 1.0]]), size, size)
        c = size // 2
        out = heat_overlay(torch.tensor([_pixel_point(cam, c, c)]), torch.tensor([1.0]), cam)
        row = (out[3, c] > 0).nonzero().squeeze(1)
        assert row.tolist() == list(range(c - half, c + half + 1)), size


# ---------------------------------------------------------------- cache and shared copy
def test_cache_is_least_recently_used() -> None:
    made: list[str] = []

    def make(v: str) -> Any:
        return lambda: made.append(v) or v

    c = _Cache(2)
    assert c.get_or("a", make("A")) == "A" and c.get_or("b", make("B")) == "B"
    assert c.get_or("a", make("X")) == "A"  # a hit: not made again, and now the most recent
    assert c.get_or("c", make("C")) == "C"  # evicts b, the least recently used
    assert list(c) == ["a", "c"] and made == ["A", "B", "C"]
    assert c.get_or("b", make("B2")) == "B2" and list(c) == ["c", "b"]


def test_shared_copy_shares_tensors_not_modules() -> None:
    model = torch.nn.Sequential(torch.nn.Linear(2, 2), torch.nn.BatchNorm1d(2))
    model.extra = torch.ones(3)  # type: ignore[assignment]  # a plain tensor attribute
    cp = _shared_copy(model)
    assert cp is not model and cp[0] is not model[0]
    assert cp[0].weight is model[0].weight and cp[1].running_mean is model[1].running_mean and cp.extra is model.extra

    class Plain:
        def __init__(self) -> None:
            self.t = torch.zeros(2)
            self.mlp = torch.nn.Linear(1, 1)

    p = Plain()
    q = _shared_copy(p)
    assert q is not p and q.t is p.t and q.mlp is not p.mlp


# ---------------------------------------------------------------- the session
@pytest.fixture(scope="module")
def small(tmp_path_factory: pytest.TempPathFactory) -> Any:
    from controlgs_adapter.scene import load_builtin_backbone, load_builtin_scene, render_planes

    scene = load_builtin_scene("ar", SIZE, views=4, test_every=4, samples=1)
    model = load_builtin_backbone("ar")
    d = tmp_path_factory.mktemp("viewer-sweep")
    adapters = {"controlgs": random_adapter(model, d / "a.controlgs.safetensors", 3),
                "blind": random_adapter(model, d / "b.controlgs.safetensors", 3, state_blind=True),
                "fov": random_adapter(model, d / "f.controlgs.safetensors", 3, modules=("foveation", "display"))}
    session = ViewerSession(model, scene.views("test"), adapters, name="tiny",
                            truth=lambda cam: render_planes(scene.planes, cam, samples=1)[0].float())
    return session, scene


def test_session_refusals(small: Any) -> None:
    session, scene = small
    with pytest.raises(InputValueError, match=r"adapter names \['ss'\] clash with the baselines"):
        ViewerSession(session.model, scene.views("test"), {"ss": "x"})
    with pytest.raises(InputValueError, match="the viewer needs at least one view"):
        ViewerSession(session.model, [], {})


def test_session_info(small: Any) -> None:
    session, _ = small
    info = session.info()
    assert info["name"] == "tiny" and info["views"] == [f"test view 0 ({SIZE}x{SIZE})"]
    assert [m["name"] for m in info["methods"]] == ["no_ss", "ss", "controlgs", "blind", "fov"]
    assert info["methods"][3] == {"name": "blind", "label": "blind"}  # no label of its own: the name
    assert info["stages"] == list(STAGES) and info["optics_modes"] == list(OPTICS_MODES)
    assert info["defaults"] == ViewState().to_json() and info["diff_gain"] == 2.0
    assert info["ranges"] == {"downsample": (1.0, 8.0), "power_saving": (0.0, 0.8), "azimuth": (-180.0, 180.0),
                              "elevation": (-80.0, 80.0)}
    assert info["orbit_truth"] is True and info["device"] == "cpu"
    assert info["extra_metrics"] == list(session.extra_metrics)


def test_session_render_strengths_diffs_and_extra(small: Any) -> None:
    session, _ = small
    out = session.render(parse_state({"downsample": 4.0, "power_saving": 0.8, "gaze": [0.0, 0.0]}, 1), tag=11)
    assert out["size"] == [SIZE, SIZE] and out["has_truth"] and out["server_ms"] >= 0
    by = {m["name"]: m for m in out["methods"]}
    assert by["no_ss"]["rendered_size"] == [SIZE // 4, SIZE // 4] and by["ss"]["rendered_size"] == [SIZE, SIZE]
    assert by["ss"]["strengths"] == {} and by["ss"]["overlay"] is None
    # resample log2(4) / log2(8) = 2/3, display 0.8 / 0.8 = 1; the state-blind ablation: 1 for every module
    s = by["controlgs"]["strengths"]
    assert s["resample"] == pytest.approx(2 / 3, abs=1e-6) and s["display"] == pytest.approx(1.0, abs=1e-6)
    lens = s["lens"]
    assert set(lens) == {"mean", "min", "max"} and lens["min"] < lens["mean"] < lens["max"]
    assert by["blind"]["strengths"] == {"lens": 1.0, "resample": 1.0, "display": 1.0}
    fov = by["fov"]["strengths"]
    assert set(fov) == {"foveation", "display"} and isinstance(fov["foveation"], dict)
    for name in ("controlgs", "blind", "fov"):  # the lens (else foveation) strength as an RGBA overlay
        assert _decode(by[name]["overlay"]).shape == (SIZE, SIZE, 4)
    # difference image: |eye - gt| x 2, clipped, within one PNG level
    tag, eyes, gt = session._last
    assert tag == 11 and gt is not None
    for name, eye in eyes.items():
        want = ((eye - gt).abs() * 2.0).clamp(0, 1).permute(1, 2, 0) * 255
        assert (_decode(by[name]["diff"]) - want).abs().max() <= 0.51, name
        assert float(eye.min()) >= 0 and float(eye.max()) <= 1
    extra = session.extra(11)
    assert set(extra) == set(by) if session.extra_metrics else extra == {}


def test_session_extra_without_truth_or_metrics(small: Any) -> None:
    session, _ = small
    truth, metrics = session.truth, session.extra_metrics
    try:
        session.truth = None
        session.render(parse_state({"azimuth": 30}, 1), tag=21)
        assert session.extra(21) == {}  # no ground truth off the dataset views
        session.truth = truth
        session.render(parse_state({}, 1), tag=22)
        session.extra_metrics = {"neg": lambda a, b: float("nan"), "one": lambda a, b: 1.0}
        got = session.extra(22)
        assert got["ss"] == {"neg": None, "one": 1.0} and len(got) == 5  # non-finite values: None
        calls: list[int] = []
        session.extra(22, lambda: calls.append(1))
        assert len(calls) == 5  # one check per method
        session.extra_metrics = {}
        assert session.extra(22) == {}
    finally:
        session.truth, session.extra_metrics = truth, metrics


# ---------------------------------------------------------------- the server's headers
def test_server_headers_and_query_strings(small: Any) -> None:
    session, _ = small
    srv = make_server(session)
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
    local = make_server(session, host="localhost")
    try:
        assert local.server_address[1] > 0
    finally:
        local.server_close()


def test_frame_cache_keeps_the_16_most_recent_cameras(small: Any) -> None:
    session, _ = small
    session._frames.clear()
    first = session._frame(parse_state({"azimuth": 1.0}, 1))
    for az in range(2, 18):  # 16 more cameras: the first one is evicted by the 17th
        session._frame(parse_state({"azimuth": float(az)}, 1))
    assert len(session._frames) == 16
    assert (0, 1.0, 0.0) not in session._frames and (0, 2.0, 0.0) in session._frames
    again = session._frame(parse_state({"azimuth": 1.0}, 1))
    assert again is not first and torch.equal(again[2], first[2])  # rendered anew, the same image
    assert session._frame(parse_state({"azimuth": 1.0}, 1)) is again  # now cached



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


def _ask(srv: Any, method: str, path: str, raw: bytes | None = None, host: str | None = None) -> tuple[int, Any]:
    conn = http.client.HTTPConnection(*srv.server_address[:2], timeout=60)
    conn.request(method, path, body=raw, headers={} if host is None else {"Host": host})
    resp = conn.getresponse()
    out = resp.status, json.loads(resp.read())
    conn.close()
    return out


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


def test_view_state_is_frozen_and_orbit_keeps_float64() -> None:
    import dataclasses

    with pytest.raises(dataclasses.FrozenInstanceError):
        ViewState().view = 1  # type: ignore[misc]
    cam = _cam_at_minus_z()
    cam64 = Camera(cam.world_to_camera.double(), cam.intrinsics, 8, 8)
    turned = orbit_camera(cam64, torch.zeros(3, dtype=torch.float64), 30.0, 0.0)
    assert turned.world_to_camera.dtype == torch.float64
    c, s = math.cos(math.radians(30)), math.sin(math.radians(30))
    # 30 degrees about up (-y): centre (0, 0, -4) -> 4 (sin 30, 0, -cos 30), exactly in float64
    assert torch.allclose(turned.center.double(), torch.tensor([4 * s, 0.0, -4 * c], dtype=torch.float64), rtol=0, atol=1e-14)
    assert torch.equal(scene_centre([cam], None), torch.zeros(3, dtype=torch.float64))
    assert scene_centre([cam], None).dtype == torch.float64
    assert scene_centre([cam], torch.ones(2, 3)).dtype == torch.float64


def test_encode_png_compresses() -> None:
    """Low compression (level 1), not none: a flat 64 x 64 image is well under its 12 kB of raw pixels."""
    from controlgs_adapter.viewer.session import encode_png

    png = base64.b64decode(encode_png(torch.full((3, 64, 64), 0.5)))
    assert png[:8] == b"\x89PNG\r\n\x1a\n" and len(png) < 1000
    assert len(base64.b64decode(encode_png(torch.full((3, 64, 64), 0.5), level=0))) > 12000  # stored: raw size


def test_session_with_a_renderer_of_its_own_and_no_adapter(small: Any) -> None:
    from controlgs_adapter.rendering import FunctionRenderer

    session, scene = small
    calls: list[int] = []

    def render(m: Any, c: Any, v: Any, bg: Any) -> torch.Tensor:
        calls.append(c.width)
        return m.render(c, v, bg).color

    plain = ViewerSession(session.model, scene.views("test"), {}, renderer=FunctionRenderer(render,
                          visible=lambda m, c: m.visible_anchors(c)))
    assert plain.methods == ["no_ss", "ss"] and plain.info()["orbit_truth"] is False
    out = plain.render(parse_state({"downsample": 4.0}, 1))  # default tag 0
    assert sorted(calls) == [SIZE // 4, SIZE] and isinstance(out["server_ms"], float)
    assert plain.extra(0) == {} or set(plain.extra(0)) == {"no_ss", "ss"}
    assert plain.background is not None and torch.equal(plain.background, scene.views("test").background)


def test_strengths_of_a_camera_that_sees_no_anchor(small: Any) -> None:
    """Looking away from the scene: no visible anchor; per-anchor strengths report 0 (mean, min, max), the
    state-blind ablation its constant 1, global ones their value; no overlay pixel."""
    session, _ = small
    cam = session.cameras[0]
    w2c = cam.world_to_camera.clone()  # turned half a circle about its own y axis: the scene is behind it
    w2c[:3, :3] = torch.diag(torch.tensor([-1.0, 1.0, -1.0])) @ w2c[:3, :3]
    w2c[:3, 3] = -(w2c[:3, :3] @ cam.center)
    blind_cam = Camera(w2c, cam.intrinsics, cam.width, cam.height)
    rs = parse_state({"downsample": 4.0, "power_saving": 0.4}, 1).runtime
    copy_, cgs = session.adapters["controlgs"]
    assert int(torch.as_tensor(session.renderer.visible(copy_, blind_cam)).sum()) == 0  # the case under test
    strengths, overlay = session._strengths(cgs, copy_, blind_cam, rs)
    assert strengths["lens"] == {"mean": 0.0, "min": 0.0, "max": 0.0}
    assert strengths["resample"] == pytest.approx(2 / 3, abs=1e-6) and strengths["display"] == pytest.approx(0.5, abs=1e-6)
    assert float(_decode(overlay)[..., 3].max()) == 0.0
    copy_, cgs = session.adapters["blind"]
    strengths, _ = session._strengths(cgs, copy_, blind_cam, rs)
    assert strengths == {"lens": 1.0, "resample": 1.0, "display": 1.0}


def test_no_ss_cache_keeps_the_32_most_recent_renders(small: Any) -> None:
    session, scene = small
    plain = ViewerSession(session.model, scene.views("test"), {})  # the two baselines only: cheap renders
    for az in range(1, 34):  # 33 orbit cameras, one no-SS render each: the first is evicted by the 33rd
        plain.render(parse_state({"azimuth": float(az), "stages": []}, 1))
    assert len(plain._small) == 32
    keys = [k[:3] for k in plain._small]
    assert (0, 1.0, 0.0) not in keys and (0, 2.0, 0.0) in keys and (0, 33.0, 0.0) in keys
