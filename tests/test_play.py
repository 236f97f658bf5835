"""``motionflows play``: the socket protocol, the root placement, and the page in a browser.

The browser tests drive the real page in headless Chromium (Debian's ``chromium`` and
``chromium-driver`` with Selenium; ``.ci/run`` installs them) against ``motionflows play``
started as a subprocess on a free port, serving the shipped ``moglow-bandai``. Without a
browser they skip, naming what is missing.
Set ``MOTIONFLOWS_UPDATE_SCREENSHOT=1`` to refresh ``docs/readme/play.png``.
"""

from __future__ import annotations

import json
import math
import os
import shutil
import signal
import subprocess
import sys
import time
import urllib.request
from pathlib import Path

import numpy as np
import pytest

from motionflows.evaluation.motion import to_global
from motionflows.play.character import RAMP_SECONDS, advance, place, ramp
from motionflows.play.protocol import LIMITS, BadMessage, parse_message

PLAYED = "pretrained:moglow-bandai"

ROOT = Path(__file__).resolve().parents[1]

# ------------------------------------------------------------------- no browser needed


def test_messages_are_clamped_or_rejected():
    msg = parse_message(
        json.dumps({"type": "control", "forward": 1e9, "sideways": -1e9, "turn": 0.5, "seq": 3})
    )
    assert msg["target"] == (LIMITS["forward"][1], LIMITS["sideways"][0], 0.5)
    assert msg["seq"] == 3
    inf = parse_message('{"type": "control", "forward": -Infinity, "turn": 1e400}')
    assert inf["target"] == (LIMITS["forward"][0], 0.0, LIMITS["turn"][1])
    huge_int = parse_message(json.dumps({"type": "control", "forward": 10**400}))
    assert huge_int["target"][0] == LIMITS["forward"][1]
    assert parse_message('{"type": "temperature", "value": 99}')["value"] == 1.5
    assert parse_message('{"type": "pause", "paused": true}') == {"type": "pause", "paused": True}
    bad = [
        None,
        b"\x00\x01",
        "not json",
        "[1, 2]",
        "x" * 10_000,
        "[" * 2000 + "]" * 2000,
        '{"type": "warp"}',
        '{"forward": 1}',
        '{"type": "control", "forward": "fast"}',
        '{"type": "control", "forward": NaN}',
        '{"type": "control", "forward": true}',
        '{"type": "control", "seq": 1.5}',
        '{"type": "pause", "paused": "yes"}',
    ]
    for raw in bad:
        with pytest.raises(BadMessage):
            parse_message(raw)


def test_streamed_placement_matches_to_global():
    """Frame by frame placement (the server) = ``to_global`` of the recording (render)."""
    rng = np.random.default_rng(0)
    pose = rng.normal(size=(30, 63)).astype(np.float32)
    control = np.stack(
        [rng.uniform(-0.05, 0.12, 30), rng.uniform(-0.03, 0.03, 30), rng.uniform(-0.2, 0.2, 30)],
        axis=-1,
    ).astype(np.float32)
    position, yaw, streamed = np.zeros(3), 0.0, []
    for p, c in zip(pose, control, strict=True):
        streamed.append(place(p, position, yaw))
        position, yaw = advance(position, yaw, c)
    expected = to_global(pose, control).reshape(30, 21, 3)
    np.testing.assert_allclose(np.stack(streamed), expected, atol=1e-5)


def test_ramp_is_a_first_order_approach():
    applied, target = np.zeros(3), np.array([1.0, -2.0, 0.5])
    steps = 20
    for _ in range(steps):
        applied = ramp(applied, target, RAMP_SECONDS / steps)
    np.testing.assert_allclose(applied, target * (1 - math.exp(-1)), rtol=1e-6)


def test_a_diverged_frame_resets_the_character_but_keeps_the_recording():
    """The engine restarts the character standing after a non-finite frame; the motion
    played before it stays in ``/record.npz`` (it was emptied, losing a whole session's
    recording to one bad frame), with the restart marked; a user's reset still empties it."""
    import jax

    from motionflows.models.moglow import MoGlow
    from motionflows.play.character import Character
    from motionflows.play.engine import Engine

    class Units:
        poison = False  # denormalize_pose gives NaN while set: a diverged frame

        def normalize_control(self, c):
            return np.asarray(c, np.float32)

        def denormalize_pose(self, x):
            x = np.asarray(x, np.float32)
            return np.full_like(x, np.nan) if self.poison else x

    units = Units()
    model = MoGlow(63, 3, tau=2, K=1, hidden=8, rngs=jax.random.key(0))
    character = Character(model, units, fps=20.0)
    messages: list[dict] = []
    engine = Engine(character, messages.append)
    for _ in range(5):
        engine._frame()
    units.poison = True
    engine._frame()
    units.poison = False
    for _ in range(2):
        engine._frame()
    errors = [m for m in messages if m["type"] == "error"]
    assert len(errors) == 1 and "recording keeps" in errors[0]["message"]
    record = character.recording()
    assert record["pose"].shape == (7, 63) and record["control"].shape == (7, 3)
    assert np.all(np.isfinite(record["pose"]))
    np.testing.assert_array_equal(record["resets"], [5])
    assert character.t == 2  # restarted: frame 0, 1 of the new episode
    character.reset()  # the user's reset: a new, empty recording
    record = character.recording()
    assert record["pose"].shape == (0, 63) and record["resets"].shape == (0,)
    # beyond the recording's limit the oldest frames go, and the marks follow them
    import motionflows.play.character as character_module

    limit, character_module.MAX_RECORD_FRAMES = character_module.MAX_RECORD_FRAMES, 4
    try:
        character.reset()
        for poison in (False, False, False, True, False, False, False):
            units.poison = poison
            engine._frame()
    finally:
        character_module.MAX_RECORD_FRAMES = limit
    record = character.recording()
    assert record["pose"].shape == (4, 63)  # frames 2..5 of the 6 played
    np.testing.assert_array_equal(record["resets"], [1])  # the restart after frame 3


def test_cli_play_reports_bad_input_in_one_line(capsys):
    from motionflows.cli import main

    assert main(["play", "/no/such/run"]) == 2
    err = capsys.readouterr().err
    assert "not a run directory" in err and "Traceback" not in err
    assert main(["play", "/no/such/run", "--port", "70000"]) == 2
    assert "--port" in capsys.readouterr().err


# -------------------------------------------------------------------------- browser


def _browser_or_skip():
    """(chromium, chromedriver) paths, or skip with what is missing."""
    for module in ("selenium", "starlette", "uvicorn", "websockets"):
        pytest.importorskip(module, reason=f"{module} missing: pip install -e '.[test,play]'")
    chromium = next(
        (
            shutil.which(n)
            for n in ("chromium", "chromium-browser", "google-chrome")
            if shutil.which(n)
        ),
        None,
    )
    driver = shutil.which("chromedriver")
    if chromium is None or driver is None:
        pytest.skip("no headless browser: apt-get install chromium chromium-driver (.ci/run does)")
    return chromium, driver


@pytest.fixture(scope="module")
def server(tmp_path_factory):
    """``motionflows play pretrained:moglow-bandai`` on a free port: (process, base URL,
    stderr file). The shipped model, the one a user plays: a tiny model trained here does not
    reliably make a gait of its own at T = 0, now that the control no longer carries one."""
    _browser_or_skip()
    log = tmp_path_factory.mktemp("play-log") / "stderr.txt"
    with open(log, "w") as err:
        proc = subprocess.Popen(
            [sys.executable, "-m", "motionflows.cli", "play", PLAYED, "--port", "0"],
            stdout=subprocess.PIPE,
            stderr=err,
            text=True,
            cwd=ROOT,
        )
    line = proc.stdout.readline()  # the URL line (after loading and compiling)
    if "http://" not in line:
        proc.kill()
        pytest.fail(f"no URL printed: {line!r}; stderr: {log.read_text()[-2000:]}")
    url = line.split("open ", 1)[1].split()[0]
    yield proc, url, log
    if proc.poll() is None:
        proc.kill()
        proc.wait()


@pytest.fixture(scope="module")
def page(server):
    chromium, driver_path = _browser_or_skip()
    from selenium import webdriver
    from selenium.webdriver.chrome.options import Options
    from selenium.webdriver.chrome.service import Service

    options = Options()
    options.binary_location = chromium
    for arg in ("--headless=new", "--no-sandbox", "--disable-dev-shm-usage", "--disable-gpu"):
        options.add_argument(arg)
    options.add_argument("--window-size=1280,800")
    driver = webdriver.Chrome(service=Service(driver_path), options=options)
    driver.get(server[1])
    _wait(driver, "return window.playStats && window.playStats.frames > 5", "first frames")
    yield driver
    driver.quit()


def _wait(driver, script: str, what: str, timeout: float = 20.0):
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        value = driver.execute_script(script)
        if value:
            return value
        time.sleep(0.05)
    raise AssertionError(f"timed out waiting for {what}")


def _last(driver) -> dict:
    return driver.execute_script("return window.playStats.last")


def _hold(driver, keys: list[str], seconds: float) -> dict:
    """Hold ``keys`` for ``seconds``; returns the last frame before they are released."""
    from selenium.webdriver.common.action_chains import ActionChains

    chain = ActionChains(driver)
    for k in keys:
        chain.key_down(k)
    chain.perform()
    time.sleep(seconds)
    last = _last(driver)
    chain = ActionChains(driver)
    for k in reversed(keys):
        chain.key_up(k)
    chain.perform()
    return last


def _reset(driver) -> int:
    """Press Reset; wait for the new episode's first frames; returns the episode number."""
    old = _last(driver)["episode"]
    driver.find_element("id", "reset").click()
    return _wait(
        driver,
        f"const f = window.playStats.last; return f.episode !== {old} && f.t > 2 && f.episode",
        "a new episode",
    )


def _local_ankles_forward(frame: dict) -> tuple[float, float]:
    """Left and right ankle positions along the root's facing (metres)."""
    j = np.asarray(frame["joints"]).reshape(21, 3)
    x, z, yaw = frame["root"][0], frame["root"][1], frame["yaw"]
    ahead = (j[:, 0] - x) * math.sin(yaw) + (j[:, 2] - z) * math.cos(yaw)
    return float(ahead[3]), float(ahead[7])  # LeftFoot, RightFoot


def test_frames_arrive_and_the_hud_shows_them(page):
    n0 = page.execute_script("return window.playStats.frames")
    time.sleep(1.0)
    n1 = page.execute_script("return window.playStats.frames")
    assert n1 - n0 >= 5, (n0, n1)  # 20 fps nominal; a loaded CI machine may be slower
    hud = page.find_element("id", "hud").text
    assert "frames/s" in hud and "fps of 20" in hud, hud


def test_forward_moves_the_root_forward_and_the_feet_alternate(page):
    slider = page.find_element("id", "temperature")  # T = 0: the model's own gait, no noise
    slider.click()
    from selenium.webdriver.common.keys import Keys

    slider.send_keys(Keys.HOME)
    _wait(page, "return window.playStats.last.temperature === 0", "temperature 0")
    episode = _reset(page)
    start = _last(page)
    end = _hold(page, ["w"], 3.5)
    assert end["episode"] == episode
    dx, dz = end["root"][0] - start["root"][0], end["root"][1] - start["root"][1]
    ahead = dx * math.sin(start["yaw"]) + dz * math.cos(start["yaw"])
    assert ahead > 2.0, (start["root"], end["root"])  # ~1.1 m/s for 3.5 s, ramped
    assert abs(end["yaw"] - start["yaw"]) < 0.05

    history = page.execute_script("return window.playStats.history")
    walking = [
        f for f in history if f["episode"] == episode and start["t"] + 20 <= f["t"] <= end["t"]
    ]
    lead = np.array([np.subtract(*_local_ankles_forward(f)) for f in walking])
    assert len(lead) > 30
    smooth = np.convolve(lead, np.ones(3) / 3, mode="valid")
    # a gait: a smooth swing (not frame-to-frame noise) of either foot in front in turn
    assert np.ptp(smooth) > 0.15, np.round(lead, 2)
    assert np.corrcoef(lead[:-1], lead[1:])[0, 1] > 0.6, np.round(lead, 2)
    signs = np.sign(smooth)
    runs, start_i = [], 0
    for i in range(1, len(signs) + 1):
        if i == len(signs) or signs[i] != signs[start_i]:
            if i - start_i >= 3:  # one foot leads for at least 0.15 s
                runs.append(signs[start_i])
            start_i = i
    switches = sum(a != b for a, b in zip(runs, runs[1:], strict=False))
    assert switches >= 3, (switches, np.round(lead, 2))


def test_shift_runs_and_turning_turns(page):
    running = _hold(page, ["w", "\ue008"], 1.2)  # \ue008: Shift
    assert running["forward"] > 1.9  # ramping towards the run speed (2.4 m/s)
    yaw0 = _last(page)["yaw"]
    _hold(page, ["a"], 2.0)
    yaw1 = _last(page)["yaw"]
    assert yaw1 - yaw0 > 1.5, (yaw0, yaw1)  # left = counter-clockwise = +yaw, ~90 deg/s
    _hold(page, ["\ue014"], 1.0)  # right arrow
    assert _last(page)["yaw"] < yaw1 - 0.4


def test_pause_holds_and_resume_continues(page):
    page.find_element("id", "pause").click()
    time.sleep(0.4)
    n0 = page.execute_script("return window.playStats.frames")
    time.sleep(0.6)
    assert page.execute_script("return window.playStats.frames") == n0
    page.find_element("id", "pause").click()
    _wait(page, f"return window.playStats.frames > {n0 + 5}", "frames after resume")


def test_the_stream_survives_malformed_messages(page):
    errors0 = page.execute_script("return window.playStats.errors")
    page.execute_script(
        """
        const s = window.play.socket;
        for (const m of ["garbage", "[1]", "{}", '{"type": "warp"}', "x".repeat(100000),
                         '{"type": "control", "forward": "fast"}',
                         '{"type": "control", "forward": NaN}',
                         '{"type": "temperature", "value": -5}',
                         '{"type": "control", "forward": 1e300, "seq": 1e12}']) s.send(m);
        s.send(new Uint8Array([0, 1, 2]));
        """
    )
    _wait(page, f"return window.playStats.errors >= {errors0 + 8}", "error replies")
    n0 = page.execute_script("return window.playStats.frames")
    _wait(page, f"return window.playStats.frames > {n0 + 10}", "frames after bad messages")
    last = _last(page)
    assert last["temperature"] == 0.0  # clamped from -5
    assert last["forward"] <= LIMITS["forward"][1] + 1e-6
    assert page.execute_script("return window.playStats.connected")


def test_a_second_tab_is_told_the_character_is_busy(page, server):
    first = page.current_window_handle
    page.switch_to.new_window("tab")
    page.get(server[1])
    text = _wait(page, "return window.playStats && window.playStats.busy", "busy message")
    assert "Another page is already steering" in text
    assert "Another page" in page.find_element("id", "message").text
    page.close()
    page.switch_to.window(first)
    n0 = page.execute_script("return window.playStats.frames")
    _wait(page, f"return window.playStats.frames > {n0 + 5}", "frames in the first tab")


def test_record_is_an_npz_that_render_reads(page, server):
    _reset(page)
    _hold(page, ["w", "a"], 2.0)
    history = page.execute_script("return window.playStats.history")
    with urllib.request.urlopen(server[1] + "record.npz", timeout=10) as response:
        path = Path(server[2]).with_name("record.npz")
        path.write_bytes(response.read())
    with np.load(path) as data:
        pose, control, fps = data["pose"], data["control"], float(data["fps"])
    assert pose.ndim == 2 and pose.shape[1] == 63 and control.shape == (len(pose), 3)
    assert fps == 20.0
    shown = [f for f in history if f["episode"] == history[-1]["episode"]][-1]
    t = shown["t"]
    assert t < len(pose)
    placed = to_global(pose[: t + 1], control[: t + 1])[t]  # what render draws for frame t
    np.testing.assert_allclose(placed, shown["joints"], atol=2e-3)

    from motionflows.cli import main

    one = path.with_name("one.npz")
    np.savez(one, pose=pose[:3], control=control[:3], fps=fps)
    assert main(["render", str(one), "--out", str(path.parent / "render")]) == 0


def test_screenshot_of_a_walk(page, server):
    _reset(page)
    slider = page.find_element("id", "temperature")
    page.execute_script(
        "arguments[0].value = 0.8; arguments[0].dispatchEvent(new Event('input'))", slider
    )
    from selenium.webdriver.common.action_chains import ActionChains

    ActionChains(page).key_down("w").perform()  # walk, turn left while walking, walk on
    time.sleep(2.5)
    _hold(page, ["a"], 1.5)
    time.sleep(1.5)
    shot = Path(server[2]).with_name("play.png")
    assert page.save_screenshot(str(shot))
    ActionChains(page).key_up("w").perform()
    assert shot.stat().st_size > 10_000
    if os.environ.get("MOTIONFLOWS_UPDATE_SCREENSHOT") == "1":
        shutil.copy(shot, ROOT / "docs" / "readme" / "play.png")


def test_closing_the_page_stops_generation_and_ctrl_c_stops_the_server(page, server):
    proc, url, log = server

    def status():
        with urllib.request.urlopen(url + "status", timeout=10) as response:
            return json.loads(response.read())

    assert status()["streaming"]
    page.get("about:blank")
    end = time.monotonic() + 10
    while status()["streaming"] and time.monotonic() < end:
        time.sleep(0.1)
    assert not status()["streaming"]
    frames = status()["frames"]
    time.sleep(0.3)
    assert status()["frames"] == frames

    proc.send_signal(signal.SIGINT)
    assert proc.wait(timeout=15) == 0
    text = log.read_text()
    assert "stopped" in text and "Traceback" not in text, text[-3000:]
