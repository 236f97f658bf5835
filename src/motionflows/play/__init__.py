"""``motionflows play``: steer a streaming model's character in real time from a web page.

    motionflows play runs/moglow/quick-1 [--port N] [--host 127.0.0.1] [--temperature T]
                                         [--foot-lock]

A local server (Starlette + uvicorn, the optional extra ``motionflows[play]``) steps the
model with ``stream_step`` at the run's fps on a thread of its own and streams each frame
over a WebSocket to a page shipped in ``static/`` (plain HTML, CSS and JavaScript drawing
on a 2D canvas; no build step, nothing fetched from the internet). The page's keyboard or
game pad sets the target control; the server ramps to it and clamps it.

Parts: ``character`` (model + standardiser + root path, one frame at a time), ``engine``
(the fixed-rate generation thread), ``protocol`` (socket messages, checked), ``server``
(routes, one page at a time).
"""

from __future__ import annotations

import json
from pathlib import Path

from motionflows.errors import RunError
from motionflows.play.character import Character


def load_character(
    run: str | Path, *, temperature: float = 1.0, seed: int = 0, foot_lock: bool = False
) -> Character:
    """The character of a run directory or ``pretrained:NAME`` (best checkpoint), compiled
    and ready to stream (``foot_lock``: see :class:`Character`)."""
    from motionflows import runs, training

    run_dir = runs.resolve_run_dir(run)
    module, config, model, _ = training.load_run(run_dir, load_data=False)
    if not hasattr(model, "stream_step"):
        raise RunError(
            f"{run_dir} is a {module.NAME} run; play needs a causal model with a streaming "
            "step (MoGlow): give a moglow run directory"
        )
    character = Character(
        model,
        training.load_standardizer(run_dir),
        float(config.data.fps),
        temperature=temperature,
        seed=seed,
        foot_lock=foot_lock,
    )
    character.warm_up()
    return character


def play(
    run: str | Path,
    *,
    host: str = "127.0.0.1",
    port: int = 0,
    temperature: float | None = None,
    seed: int = 0,
    foot_lock: bool = False,
) -> None:
    """Load ``run``, print the page's URL and serve it until Ctrl-C (opens nothing).

    ``temperature`` None: the one the model was validated at (``pretrained.json`` of a
    shipped model), else 1.
    """
    from motionflows import runs
    from motionflows.play import server
    from motionflows.play.protocol import TEMPERATURE_RANGE
    from motionflows.pretrained.model import INFO_FILE

    server.check_installed()
    if not 0 <= int(port) <= 65535:
        raise RunError(f"--port must be in 0..65535 (0: a free port), got {port}")
    run_dir = runs.resolve_run_dir(run)
    if temperature is None:
        info = run_dir / INFO_FILE
        found = json.loads(info.read_text()) if info.is_file() else {}
        temperature = found.get("temperature", 1.0)
    lo, hi = TEMPERATURE_RANGE
    if not lo <= float(temperature) <= hi:
        raise RunError(f"--temperature must be in [{lo:g}, {hi:g}], got {temperature:g}")
    try:  # before the model loads, so a busy port fails at once
        sock = server.bind(host, int(port))
    except OSError as err:
        raise RunError(str(err)) from None
    try:
        character = load_character(run_dir, temperature=temperature, seed=seed, foot_lock=foot_lock)
        server.serve(character, sock=sock, info={"run": str(run_dir)})
    finally:
        sock.close()


__all__ = ["Character", "load_character", "play"]
