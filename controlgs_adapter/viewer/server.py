"""The viewer's HTTP server: the standard library's ``ThreadingHTTPServer`` on the loopback
interface (no dependency; nothing is reachable from another machine), JSON endpoints and the page's
three static files, which ship inside the package and are served by name from memory (no path is
ever mapped to the file system).

Endpoints:

- ``GET /`` and ``GET /static/{index.html, viewer.js, viewer.css}``: the page;
- ``GET /api/info``: the scene, its views, methods, stages and slider ranges;
- ``POST /api/render`` (a state, :func:`~controlgs_adapter.viewer.session.parse_state`): every
  method's images, PSNR / SSIM and strengths, with its ``generation``; 409 when a newer request
  superseded it, 400 with ``{"error": ...}`` for a bad state;
- ``POST /api/extra`` ``{"generation": g}``: the slower metrics (FLIP) of render ``g`` (409 when stale).

One worker thread renders; every render request takes the next generation number, and work of an
older generation is dropped when it reaches the worker or between two methods (:class:`Generations`).
"""

from __future__ import annotations

import json
import re
import sys
import threading
from concurrent.futures import ThreadPoolExecutor
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from importlib import resources
from typing import Any, Callable

from ..checks import brief
from ..errors import InputValueError
from .session import Superseded, ViewerSession, parse_state

__all__ = ["STATIC_FILES", "Generations", "ViewerServer", "make_server"]

#: the page's files (controlgs_adapter/viewer/static/) and their content types: nothing else is served
STATIC_FILES: dict[str, str] = {"index.html": "text/html; charset=utf-8", "viewer.js": "text/javascript; charset=utf-8",
                                "viewer.css": "text/css; charset=utf-8"}
MAX_BODY = 64 * 1024
LOOPBACK = ("127.0.0.1", "localhost", "[::1]")
_PORT = re.compile(r":\d*$")  # a Host header's port (none in a bare "[::1]")


class Generations:
    """A request counter: :meth:`next` starts a request, :meth:`check` raises :class:`Superseded` once
    a later one started."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self.current = 0

    def next(self) -> int:
        with self._lock:
            self.current += 1
            return self.current

    def check(self, generation: int) -> None:
        if generation != self.current:
            raise Superseded(f"request {generation} was superseded by {self.current}")


class ViewerServer(ThreadingHTTPServer):
    """The server holding the session, the render worker and the static files."""

    daemon_threads = True
    #: the bound (host, port): an IPv4 loopback address, whose host getsockname() gives as a str
    server_address: tuple[str, int]

    def __init__(self, session: ViewerSession, port: int = 0, host: str = "127.0.0.1") -> None:
        if host not in ("127.0.0.1", "localhost"):
            raise InputValueError(f"the viewer binds to the loopback interface only, got host {host!r}")
        super().__init__((host, port), _Handler)
        self.session = session
        self.generations = Generations()
        self.worker = ThreadPoolExecutor(max_workers=1, thread_name_prefix="controlgs-view")
        folder = resources.files("controlgs_adapter.viewer") / "static"
        self.static = {name: (folder / name).read_bytes() for name in STATIC_FILES}

    def handle_error(self, request: Any, client_address: Any) -> None:
        """A client that hung up mid-answer (a refused over-long request, a closed tab) is not a server
        error: no traceback for it; anything else keeps the standard report."""
        if isinstance(sys.exc_info()[1], ConnectionError):
            return
        super().handle_error(request, client_address)

    @property
    def url(self) -> str:
        host, port = self.server_address[:2]
        return f"http://{host}:{port}/"

    def run(self, job: Callable[[Callable[[], None]], Any], generation: int) -> Any:
        """``job(check)`` on the worker thread, dropped if ``generation`` is superseded before it starts
        or at any ``check()``; returns its result (raises :class:`Superseded`)."""
        def task() -> Any:
            check = lambda: self.generations.check(generation)  # noqa: E731
            check()
            return job(check)

        return self.worker.submit(task).result()

    def server_close(self) -> None:
        super().server_close()
        self.worker.shutdown(wait=True, cancel_futures=True)


class _Handler(BaseHTTPRequestHandler):
    server: ViewerServer
    protocol_version = "HTTP/1.1"

    def log_message(self, format: str, *args: Any) -> None:  # noqa: A002 - quiet: the page polls often
        return

    def _send(self, status: int, body: bytes, content_type: str) -> None:
        try:
            self.send_response(status)
            self.send_header("Content-Type", content_type)
            self.send_header("Content-Length", str(len(body)))
            self.send_header("Cache-Control", "no-store")
            self.send_header("X-Content-Type-Options", "nosniff")
            self.end_headers()
            self.wfile.write(body)
        except (BrokenPipeError, ConnectionResetError):  # the page aborted a stale request
            self.close_connection = True

    def _json(self, status: int, data: Any) -> None:
        self._send(status, json.dumps(data, allow_nan=False).encode(), "application/json")

    def _host_ok(self) -> bool:
        """Refuse requests addressed to another host name (DNS rebinding)."""
        host = _PORT.sub("", self.headers.get("Host") or "")
        if host in LOOPBACK:
            return True
        self._json(403, {"error": f"host {host!r} refused: the viewer answers loopback addresses only"})
        return False

    def do_GET(self) -> None:  # noqa: N802
        if not self._host_ok():
            return
        path = self.path.split("?", 1)[0]
        if path == "/api/info":
            self._json(200, self.server.session.info())
            return
        name = "index.html" if path == "/" else path[len("/static/"):] if path.startswith("/static/") else None
        if name in STATIC_FILES:
            self._send(200, self.server.static[name], STATIC_FILES[name])
        else:
            self._json(404, {"error": f"no such page: {path!r} (the viewer serves only / and its static files)"})

    def _body(self) -> Any:
        try:
            length = int(self.headers.get("Content-Length", "0"))
        except ValueError:
            raise InputValueError("bad Content-Length") from None
        if not 0 < length <= MAX_BODY:
            raise InputValueError(f"the request body must be a JSON object of at most {MAX_BODY} bytes")
        try:
            return json.loads(self.rfile.read(length))
        except (UnicodeDecodeError, ValueError) as e:
            raise InputValueError(f"the request body is not JSON ({e})") from None
        except RecursionError:  # any nesting depth: a 400, never a 500
            raise InputValueError("the request body is nested too deeply (a state is a JSON object of numbers, "
                                  "strings and short lists)") from None

    def do_POST(self) -> None:  # noqa: N802
        if not self._host_ok():
            return
        path = self.path.split("?", 1)[0]
        if path not in ("/api/render", "/api/extra"):
            self._json(404, {"error": f"no such endpoint: {path!r}"})
            return
        server, session = self.server, self.server.session
        try:
            body = self._body()
            if path == "/api/render":
                state = parse_state(body, len(session.cameras))
                generation = server.generations.next()
                result = server.run(lambda check: session.render(state, check, generation), generation)
                result["generation"] = generation
            else:
                tag = body.get("generation") if isinstance(body, dict) else None
                if isinstance(tag, bool) or not isinstance(tag, int):
                    raise InputValueError(f"/api/extra takes {{\"generation\": int}}, got {brief(body)}")
                result = {"generation": tag, "metrics": server.run(lambda check: session.extra(tag, check), tag)}
            answer = json.dumps(result, allow_nan=False).encode()  # a NaN is a 500, not a dropped connection
        except Superseded as e:
            self._json(409, {"superseded": True, "error": str(e)})
        except InputValueError as e:
            self._json(400, {"error": str(e)})
        except Exception as e:  # the page shows the message; the server keeps serving
            self._json(500, {"error": f"{type(e).__name__}: {e}"})
        else:
            self._send(200, answer, "application/json")


def make_server(session: ViewerSession, port: int = 0, host: str = "127.0.0.1") -> ViewerServer:
    """A :class:`ViewerServer` for ``session`` on ``host:port`` (port 0: a free one); call
    ``serve_forever()`` (in a thread for tests) and ``shutdown()`` / ``server_close()`` at the end."""
    return ViewerServer(session, port, host)
