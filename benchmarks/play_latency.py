"""``motionflows play`` latency: control message -> the first frame that applies it; prints JSON.

The real server (uvicorn + Starlette + the engine thread) runs in this process on a free
port; a WebSocket client sends a control change at a random phase of the frame clock about
twice a second (walk, stop, turn left, ...), as a key press would, and times the arrival of
the first frame whose ``ack`` is that message. Reported: latency median / p95 / max (ms), the
model's step time, the frames per second the client received, the ticks the engine missed
(``late``) and whether it keeps up at the run's fps (at least 97 % of the nominal rate and
fewer than 1 % late ticks). The browser adds its own key-event and paint time (under one
display frame, 16 ms at 60 Hz) on top.

    python benchmarks/play_latency.py                       # paper-size MoGlow, untrained
    python benchmarks/play_latency.py runs/moglow/quick-1   # or pretrained:moglow-bandai
    python benchmarks/play_latency.py --presses 60 --quick  # a K=4, 128-unit model

An untrained model times the same as a trained one of its size (the step is the same
computation); only a run directory gives motion worth watching.
"""

from __future__ import annotations

import argparse
import json
import os
import random
import statistics
import sys
import threading
import time

import numpy as np

from motionflows.bench import describe_machine


def paper_size_character(quick: bool):
    """An untrained MoGlow of the paper's size (or the quick preset's) with a unit
    standardiser: the step costs what a trained model of that size costs."""
    import jax

    from motionflows import runs
    from motionflows.data.names import CONTROL_DIM, POSE_DIM
    from motionflows.data.pipeline import Standardizer
    from motionflows.play.character import Character

    module = runs.resolve_experiment("moglow")
    config = module.PRESETS["quick" if quick else "paper"]
    model = module.build(config, key=jax.random.key(0))
    unit = Standardizer(
        np.zeros(POSE_DIM), np.ones(POSE_DIM), np.zeros(CONTROL_DIM), np.ones(CONTROL_DIM)
    )
    character = Character(model, unit, config.data.fps, temperature=0.0)
    character.warm_up()
    size = {"K": config.K, "hidden": config.hidden, "layers": config.layers, "tau": config.tau}
    return character, size


def start_server(character):
    """The play app served by uvicorn on a thread; returns (server, thread, ws URL)."""
    import uvicorn

    from motionflows.play.server import bind, create_app, url_of

    sock = bind("127.0.0.1", 0)
    config = uvicorn.Config(create_app(character), log_level="warning", lifespan="on")
    server = uvicorn.Server(config)
    thread = threading.Thread(target=server.run, kwargs={"sockets": [sock]}, daemon=True)
    thread.start()
    while not server.started:
        time.sleep(0.05)
    return server, thread, url_of(sock).replace("http://", "ws://") + "ws"


TARGETS = [(1.1, 0.0, 0.0), (0.0, 0.0, 0.0), (1.1, 0.0, 1.57), (2.4, 0.0, 0.0), (0.0, 0.5, 0.0)]


def measure(url: str, presses: int, seed: int = 0) -> dict:
    from websockets.sync.client import connect

    rng = random.Random(seed)
    latencies, steps, arrivals, frames = [], [], [], []

    def read(ws, timeout: float) -> dict | None:
        message = json.loads(ws.recv(timeout=timeout))
        if message.get("type") != "frame":
            return None
        arrivals.append(time.perf_counter())
        steps.append(message["model_ms"])
        frames.append(message)
        return message

    with connect(url) as ws:
        hello = json.loads(ws.recv())
        fps = float(hello["fps"])
        deadline = time.perf_counter() + 1.0  # settle: the first frames
        while time.perf_counter() < deadline:
            json.loads(ws.recv())
        for seq in range(1, presses + 1):
            pause_until = time.perf_counter() + rng.uniform(0.3, 0.7)
            while (remaining := pause_until - time.perf_counter()) > 0:  # read meanwhile
                try:
                    read(ws, remaining)
                except TimeoutError:  # the press lands between frames, not right after one
                    break
            forward, sideways, turn = TARGETS[seq % len(TARGETS)]
            sent = time.perf_counter()
            ws.send(
                json.dumps(
                    {
                        "type": "control",
                        "forward": forward,
                        "sideways": sideways,
                        "turn": turn,
                        "seq": seq,
                        "sent": sent * 1e3,
                    }
                )
            )
            while True:
                frame = read(ws, 5.0)
                if frame is not None and frame["ack"] >= seq:
                    latencies.append(1e3 * (arrivals[-1] - sent))
                    break
    last = frames[-1]
    span = arrivals[-1] - arrivals[0]
    # frames received per second over the timed part (all frames: the loop reads them all)
    received = (len(arrivals) - 1) / span if span > 0 else 0.0
    ticks = last["t"] + 1 + last["late"]
    return {
        "fps_nominal": fps,
        "presses": presses,
        "latency_ms": {
            "median": round(statistics.median(latencies), 1),
            "p95": round(float(np.percentile(latencies, 95)), 1),
            "max": round(max(latencies), 1),
        },
        "model_step_ms": {
            "median": round(statistics.median(steps), 2),
            "p95": round(float(np.percentile(steps, 95)), 2),
        },
        "frames": last["t"] + 1,
        "late_ticks": last["late"],
        "dropped": last.get("dropped", 0),
        "received_fps_while_timing": round(received, 2),
        "keeps_up": bool(last["late"] < 0.01 * ticks),
    }


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("run", nargs="?", help="run directory or pretrained:NAME")
    parser.add_argument("--quick", action="store_true", help="a quick-preset-size model")
    parser.add_argument("--presses", type=int, default=30, help="control changes to time")
    args = parser.parse_args(argv)
    if args.presses < 1:
        parser.error(f"--presses must be >= 1, got {args.presses}")
    if args.run and args.quick:
        parser.error("--quick sizes the untrained model; a run has its own size: drop one")
    if args.run:
        from motionflows.errors import RunError
        from motionflows.play import load_character

        try:
            character = load_character(args.run, temperature=1.0)
        except RunError as err:
            print(f"error: {err}", file=sys.stderr)
            return 2
        model = {"run": args.run}
    else:
        character, model = paper_size_character(args.quick)
        model = {"untrained": "quick" if args.quick else "paper", **model}
    server, thread, url = start_server(character)
    try:
        result = measure(url, args.presses)
    finally:
        server.should_exit = True
        thread.join(10)
    result["keeps_up"] = bool(
        result["keeps_up"] and result["received_fps_while_timing"] >= 0.97 * result["fps_nominal"]
    )
    machine = {**describe_machine(), "load_average_1_5_15": list(os.getloadavg())}
    report = {"benchmark": "play_latency", "model": model, **result, "machine": machine}
    print(json.dumps(report, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
