"""The local web server of ``motionflows play``: Starlette routes served by uvicorn.

Routes: ``/`` the page (``static/index.html``), ``/static/*`` its script and style,
``/ws`` the socket (``motionflows.play.protocol``), ``/record.npz`` the motion since the
last reset, at most its last 20 minutes (``pose`` (T, 63) root-frame metres, ``control``
(T, 3) m/frame and rad/frame, ``fps``: what ``motionflows render`` reads), ``/status`` a
small JSON health report.

One page at a time: the first socket owns the character; a second one gets a ``busy``
message ("another page is steering ...") and is closed with code 4409, and the page says
so. Opening the page starts a fresh character; closing it stops generation (the engine
thread ends). Ctrl-C stops uvicorn, which closes the socket (code 1012) and so the engine.
"""

from __future__ import annotations

import asyncio
import contextlib
import io
import json
import socket
import sys
from collections import deque
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from motionflows.data import controls
from motionflows.data.names import FOOT_JOINTS, JOINT_NAMES, PARENTS
from motionflows.play.character import RAMP_SECONDS, Character
from motionflows.play.engine import Engine
from motionflows.play.protocol import (
    BUSY_CLOSE_CODE,
    LIMITS,
    TEMPERATURE_RANGE,
    BadMessage,
    parse_message,
)

if TYPE_CHECKING:
    from starlette.websockets import WebSocket

STATIC = Path(__file__).resolve().parent / "static"
OUTBOX_FRAMES = 8
"""Frames waiting for a slow socket beyond this are dropped (oldest first) and counted."""
TURN_RATE = np.pi / 2
"""Keyboard turn rate, rad/s (90 degrees a second)."""
BUSY_MESSAGE = (
    "Another page is already steering this character. Close that tab (or window) and "
    "reload this one; the server serves one page at a time."
)


def _missing_stack() -> str | None:
    for name in ("starlette", "uvicorn", "websockets"):
        try:
            __import__(name)
        except ImportError:
            return name
    return None


def check_installed() -> None:
    """Raise ``ImportError`` naming the fix if the optional web stack is missing."""
    missing = _missing_stack()
    if missing:
        raise ImportError(
            f"motionflows play needs the optional web stack ({missing} is missing): "
            "pip install 'motionflows[play]'"
        )


class _Session:
    """Which page (if any) owns the character, and its engine."""

    def __init__(self, character: Character, info: dict):
        self.character = character
        self.info = info
        self.engine: Engine | None = None
        self.pages = 0  # sockets that owned the character so far


def hello_message(session: _Session) -> dict[str, Any]:
    ch = session.character
    return {
        "type": "hello",
        **session.info,
        "fps": ch.fps,
        "joint_names": list(JOINT_NAMES),
        "parents": list(PARENTS),
        "foot_joints": list(FOOT_JOINTS),
        "limits": {k: list(v) for k, v in LIMITS.items()},
        "temperature": ch.temperature,
        "temperature_range": list(TEMPERATURE_RANGE),
        "ramp_seconds": RAMP_SECONDS,
        "speeds": {  # m/s and rad/s the keys ask for (the control presets' speeds)
            "walk": controls.WALK,
            "run": controls.RUN,
            "back": controls.BACK,
            "side": controls.SIDE,
            "turn": TURN_RATE,
        },
    }


class _Outbox:
    """One socket's outgoing messages: the newest ``OUTBOX_FRAMES``, the dropped ones counted."""

    def __init__(self, ws: WebSocket):
        self.ws = ws
        self.loop = asyncio.get_running_loop()
        self.messages: deque = deque(maxlen=OUTBOX_FRAMES)
        self.wake = asyncio.Event()
        self.dropped = 0

    def push(self, message: dict) -> None:  # on the event loop
        """Queue ``message``, dropping (and counting) the oldest when the queue is full."""
        if len(self.messages) == self.messages.maxlen:
            self.dropped += 1
        self.messages.append(message)
        self.wake.set()

    def emit(self, message: dict) -> None:  # on the engine thread
        """Hand ``message`` to the event loop, which queues it (nothing once it is closing)."""
        with contextlib.suppress(RuntimeError):  # the loop is closing
            self.loop.call_soon_threadsafe(self.push, message)

    async def send_loop(self) -> None:
        """Send the queued messages as they come, each frame with the dropped count so far."""
        while True:
            await self.wake.wait()
            self.wake.clear()
            while self.messages:
                message = self.messages.popleft()
                if message["type"] == "frame":
                    message["dropped"] = self.dropped
                await self.ws.send_text(json.dumps(message))


async def _receive_loop(ws: WebSocket, engine: Engine, outbox: _Outbox) -> None:
    """Submit the page's messages to the engine until it disconnects; report rejected ones."""
    while True:
        message = await ws.receive()
        if message["type"] == "websocket.disconnect":
            break
        raw = message.get("text")
        try:
            engine.submit(parse_message(raw if raw is not None else message.get("bytes")))
        except BadMessage as err:
            outbox.push({"type": "error", "message": f"message rejected: {err}"})
        except Exception as err:  # noqa: BLE001 - a bad message never ends the stream
            outbox.push({"type": "error", "message": f"message rejected ({err!r:.80})"})


class _Routes:
    """The app's endpoints over one session (Starlette takes bound methods as endpoints)."""

    def __init__(self, session: _Session):
        self.session = session

    async def index(self, request):
        """The page (``static/index.html``), never cached."""
        from starlette.responses import FileResponse

        return FileResponse(STATIC / "index.html", headers={"Cache-Control": "no-store"})

    async def status(self, request):
        """A small JSON health report: streaming or not, pages so far, frames, episode."""
        from starlette.responses import JSONResponse

        engine, character = self.session.engine, self.session.character
        return JSONResponse(
            {
                "streaming": engine is not None and engine.running,
                "pages": self.session.pages,
                "frames": character.t,
                "episode": character.episode,
            }
        )

    async def record(self, request):
        """The motion since the last reset as an ``.npz`` download."""
        from starlette.responses import Response

        character = self.session.character
        buf = io.BytesIO()
        np.savez(buf, **character.recording(), temperature=np.float32(character.temperature))
        return Response(
            buf.getvalue(),
            media_type="application/octet-stream",
            headers={"Content-Disposition": 'attachment; filename="motionflows-play.npz"'},
        )

    async def socket(self, ws: WebSocket) -> None:
        """The page's socket: ``busy`` if another page owns the character, else the stream."""
        from starlette.websockets import WebSocketDisconnect

        session = self.session
        await ws.accept()
        if session.engine is not None:
            await ws.send_text(json.dumps({"type": "busy", "message": BUSY_MESSAGE}))
            await ws.close(code=BUSY_CLOSE_CODE)
            return
        outbox = _Outbox(ws)
        session.character.reset()
        engine = session.engine = Engine(session.character, outbox.emit)
        session.pages += 1
        sender = None
        try:
            await ws.send_text(json.dumps(hello_message(session)))
            engine.start()
            sender = asyncio.create_task(outbox.send_loop())
            # a send to a page that has gone ends the task; the receive loop then sees the
            # disconnect, so its exception is expected and only retrieved here
            sender.add_done_callback(lambda task: task.cancelled() or task.exception())
            await _receive_loop(ws, engine, outbox)
        except WebSocketDisconnect:
            pass
        finally:
            engine.stop()
            session.engine = None
            if sender is not None:
                sender.cancel()

    @contextlib.asynccontextmanager
    async def lifespan(self, app):
        """Run the app; on shutdown stop the engine of a page still open (Ctrl-C)."""
        yield
        if self.session.engine is not None:  # Ctrl-C with a page open
            self.session.engine.stop()


def create_app(character: Character, *, info: dict | None = None):
    """The Starlette app serving ``character`` (compiled already: see ``warm_up``)."""
    check_installed()
    from starlette.applications import Starlette
    from starlette.routing import Mount, Route, WebSocketRoute
    from starlette.staticfiles import StaticFiles

    endpoints = _Routes(_Session(character, dict(info or {})))
    routes = [
        Route("/", endpoints.index),
        Route("/status", endpoints.status),
        Route("/record.npz", endpoints.record),
        WebSocketRoute("/ws", endpoints.socket),
        Mount("/static", StaticFiles(directory=STATIC), name="static"),
    ]
    return Starlette(routes=routes, lifespan=endpoints.lifespan)


def bind(host: str, port: int) -> socket.socket:
    """A listening TCP socket on ``host:port`` (port 0: a free one)."""
    family = socket.AF_INET6 if ":" in host else socket.AF_INET
    sock = socket.socket(family, socket.SOCK_STREAM)
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
    try:
        sock.bind((host, port))
    except OSError as err:
        sock.close()
        raise OSError(
            f"cannot listen on {host}:{port} ({err.strerror}); check --host or pick another --port"
        ) from None
    sock.listen(64)
    sock.setblocking(False)
    return sock


def url_of(sock: socket.socket) -> str:
    host, port = sock.getsockname()[:2]
    return f"http://[{host}]:{port}/" if ":" in host else f"http://{host}:{port}/"


def serve(
    character: Character,
    *,
    host: str = "127.0.0.1",
    port: int = 0,
    sock: socket.socket | None = None,
    info: dict | None = None,
) -> None:
    """Serve the page until Ctrl-C on ``sock`` (default: ``bind(host, port)``); prints the
    URL (on stdout) and opens nothing."""
    check_installed()
    import uvicorn

    app = create_app(character, info=info)
    sock = bind(host, port) if sock is None else sock
    config = uvicorn.Config(
        app,
        log_level="warning",
        ws_max_size=1 << 20,  # a larger message closes the socket; parse_message caps at 4 KiB
        timeout_graceful_shutdown=3,
        lifespan="on",
    )
    server = uvicorn.Server(config)
    print(f"motionflows play: open {url_of(sock)} in a browser (Ctrl-C stops)", flush=True)
    try:
        server.run(sockets=[sock])
    except KeyboardInterrupt:  # uvicorn re-raises the Ctrl-C it handled
        pass
    finally:
        sock.close()
    print("motionflows play: stopped", file=sys.stderr, flush=True)
