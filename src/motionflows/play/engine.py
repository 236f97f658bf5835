"""The generation loop: a character stepped at its fps on a thread of its own.

The socket side never touches the character: it ``submit``s checked commands
(``protocol.parse_message``), which the loop applies at the start of the next tick, and it
receives each frame through ``emit`` (called on the engine thread; the server hands it to
the event loop). So a slow frame never blocks the page or the socket.

Timing: ticks are ``1/fps`` apart on a monotonic clock. A frame that overruns its tick is
sent as soon as it is ready and the next one starts at once; ticks overrun by a whole
period are skipped (the page holds the last pose; no burst of catch-up frames) and counted
in ``late``.
"""

from __future__ import annotations

import math
import queue
import threading
import time
from collections.abc import Callable
from typing import Any

import numpy as np

from motionflows.play.character import Character


def frame_message(frame: dict, *, episode: int, extra: dict) -> dict[str, Any]:
    """A ``Character.step`` frame as the JSON-ready ``frame`` message of the protocol."""
    applied = frame["applied"]
    return {
        "type": "frame",
        "t": frame["t"],
        "episode": episode,
        "joints": np.round(frame["joints"], 4).reshape(-1).tolist(),  # world metres
        "root": [round(float(frame["position"][0]), 4), round(float(frame["position"][2]), 4)],
        "yaw": round(float(frame["yaw"]), 5),
        "forward": round(float(applied[0]), 3),  # m/s
        "sideways": round(float(applied[1]), 3),  # m/s
        "turn": round(float(applied[2]), 4),  # rad/s
        **extra,
    }


class Engine:
    """Steps ``character`` at its fps on a daemon thread until :meth:`stop`.

    ``emit(message)`` receives every outgoing message (``frame`` and ``error`` dicts) on
    the engine thread and must not block.
    """

    def __init__(self, character: Character, emit: Callable[[dict], None]):
        self.character = character
        self.emit = emit
        self.commands: queue.SimpleQueue = queue.SimpleQueue()
        self.paused = False
        self.late = 0
        self.model_ms = 0.0  # running mean of the step's wall time
        self.ack, self.sent = -1, 0.0
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None

    def submit(self, command: dict) -> None:
        """Queue a checked command (thread-safe); applied at the next tick."""
        self.commands.put(command)

    def start(self) -> None:
        self._thread = threading.Thread(target=self._run, name="motionflows-play", daemon=True)
        self._thread.start()

    def stop(self, timeout: float = 5.0) -> None:
        """Stop after the frame in progress (if any) and wait for the thread."""
        self._stop.set()
        if self._thread is not None and self._thread is not threading.current_thread():
            self._thread.join(timeout)

    @property
    def running(self) -> bool:
        return self._thread is not None and self._thread.is_alive()

    def _apply(self, command: dict) -> None:
        kind = command["type"]
        if kind == "control":
            self.character.target = np.asarray(command["target"], np.float64)
            self.ack, self.sent = command["seq"], command["sent"]
        elif kind == "pause":
            self.paused = command["paused"]
        elif kind == "reset":
            self.character.reset()
        elif kind == "temperature":
            self.character.temperature = command["value"]

    def _drain(self) -> None:
        while True:
            try:
                self._apply(self.commands.get_nowait())
            except queue.Empty:
                return

    def _frame(self) -> None:
        ch = self.character
        start = time.perf_counter()
        try:
            frame = ch.step()
        except FloatingPointError as err:
            ch.reset(keep_recording=True)  # the motion before it stays downloadable
            self.emit(
                {
                    "type": "error",
                    "message": f"{err}; reset to standing (the recording keeps the motion "
                    "before it)",
                }
            )
            return
        ms = 1e3 * (time.perf_counter() - start)
        self.model_ms = ms if self.model_ms == 0 else 0.9 * self.model_ms + 0.1 * ms
        extra = {
            "model_ms": round(ms, 2),
            "model_fps": round(1e3 / max(self.model_ms, 1e-3), 1),
            "late": self.late,
            "ack": self.ack,
            "sent": self.sent,
            "temperature": ch.temperature,
        }
        self.emit(frame_message(frame, episode=ch.episode, extra=extra))

    def _run(self) -> None:
        period = 1.0 / self.character.fps
        next_tick = time.perf_counter()
        try:
            while not self._stop.is_set():
                delay = next_tick - time.perf_counter()
                if delay > 0 and self._stop.wait(delay):
                    break
                self._drain()
                if not self.paused:
                    self._frame()
                next_tick += period
                missed = math.floor((time.perf_counter() - next_tick) / period)
                if missed > 0:  # overran by whole ticks: hold, skip them
                    if not self.paused:
                        self.late += missed
                    next_tick += missed * period
        except Exception as err:  # noqa: BLE001 - reported to the page, then the loop ends
            self.emit({"type": "error", "fatal": True, "message": f"generation stopped: {err}"})
