"""Scale-out that is tested: two real processes on 127.0.0.1 train like one process.

The processes are started exactly as the README says (``MOTIONFLOWS_COORDINATOR`` /
``_NUM_PROCESSES`` / ``_PROCESS_ID`` and the same ``motionflows train`` command), train a tiny
MoGlow, and are compared with one process at the same global batch. Also here: simulated
CPU devices whose all-reduce deadlocked with XLA:CPU's default thread pool.
"""

from __future__ import annotations

import json
import os
import socket
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[1]
TIMEOUT_S = 240  # per launch; a hang fails the test instead of stalling CI


def _distributed_available() -> bool:
    try:
        import jax.distributed  # noqa: F401
        from jax.experimental import multihost_utils  # noqa: F401
    except ImportError:
        return False
    return True


pytestmark = pytest.mark.skipif(
    not _distributed_available(), reason="jax.distributed is not available in this JAX"
)

# The quick preset shrunk to seconds: one flow step of an 8-unit LSTM, 12 synthetic clips.
TINY = [
    "K=1",
    "hidden=8",
    "layers=1",
    "data.synthetic_clips=12",
    "train.batch_size=8",
    "train.lr=3e-4",
    "train.warmup_steps=0",
    "train.schedule=constant",  # the same lr per step whatever train.steps is
    "train.log_every=1",
    "train.eval_every=1000",
    "train.eval_batches=1",
    "train.checkpoint_every=2",
]


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _env(base: Path, **extra: str) -> dict[str, str]:
    env = {k: v for k, v in os.environ.items() if not k.startswith(("MOTIONFLOWS_", "XLA_"))}
    env.update(
        JAX_PLATFORMS="cpu",
        JAX_DISABLE_MOST_OPTIMIZATIONS="1",  # compiles twice as fast; values are checked here
        MOTIONFLOWS_CACHE=str(base / "cache"),
        **extra,
    )
    return env


def _train_cmd(runs_dir: Path, steps: int, *more: str) -> list[str]:
    return [
        sys.executable,
        "-m",
        "motionflows.cli",
        "train",
        "moglow",
        "--steps",
        str(steps),
        "--set",
        *TINY,
        "--runs-dir",
        str(runs_dir),
        "--run-name",
        "tiny",
        "--no-eval",
        "--no-progress",
        *more,
    ]


def _launch(cmds: list[list[str]], envs: list[dict]) -> list[tuple[int, str]]:
    """Start every command at once; wait (bounded) for all; kill all on any failure."""
    procs = []
    try:
        for cmd, env in zip(cmds, envs, strict=True):
            procs.append(
                subprocess.Popen(
                    cmd,
                    cwd=ROOT,
                    env=env,
                    stdout=subprocess.PIPE,
                    stderr=subprocess.STDOUT,
                    text=True,
                )
            )
        deadline = time.monotonic() + TIMEOUT_S
        results = []
        for p in procs:
            out, _ = p.communicate(timeout=max(1.0, deadline - time.monotonic()))
            results.append((p.returncode, out))
        return results
    finally:
        for p in procs:
            if p.poll() is None:
                p.kill()
                p.wait()


def _two_processes(cmds: list[list[str]], base: Path, **extra: str) -> list[tuple[int, str]]:
    port = _free_port()
    envs = [
        _env(
            base,
            MOTIONFLOWS_COORDINATOR=f"127.0.0.1:{port}",
            MOTIONFLOWS_NUM_PROCESSES="2",
            MOTIONFLOWS_PROCESS_ID=str(i),
            **extra,
        )
        for i in range(2)
    ]
    return _launch(cmds, envs)


def _losses(run_dir: Path) -> dict[int, float]:
    rows = [json.loads(line) for line in (run_dir / "metrics.jsonl").read_text().splitlines()]
    return {r["step"]: r["loss"] for r in rows if "loss" in r}


def _trace(folder: Path, process: int) -> dict[int, dict[int, str]]:
    lines = (folder / f"process{process}.jsonl").read_text().splitlines()
    return {d["step"]: {int(k): v for k, v in d["rows"].items()} for d in map(json.loads, lines)}


def _files(folder: Path) -> list[Path]:
    return sorted(p for p in folder.rglob("*") if p.is_file()) if folder.exists() else []


@pytest.fixture(scope="module")
def runs(tmp_path_factory):
    """One process for 6 steps; two processes for 4 steps (process 1 pointed at its own,
    empty runs directory); both processes resumed to step 6 on process 0's directory."""
    base = tmp_path_factory.mktemp("multiprocess")
    [(rc, out)] = _launch(
        [_train_cmd(base / "one", 6)],
        [_env(base, MOTIONFLOWS_TRACE_BATCHES=str(base / "trace_one"))],
    )
    assert rc == 0, out[-3000:]
    shared, own = base / "two", base / "two_p1"
    first = _two_processes(
        [_train_cmd(shared, 4), _train_cmd(own, 4)],
        base,
        MOTIONFLOWS_TRACE_BATCHES=str(base / "trace_two"),
    )
    for rc, out in first:
        assert rc == 0, out[-3000:]
    own_files = _files(own)  # before the resume, which shares process 0's directory
    resumed = _two_processes([_train_cmd(shared, 6, "--resume")] * 2, base)
    for rc, out in resumed:
        assert rc == 0, out[-3000:]
    return {
        "base": base,
        "one": base / "one" / "moglow" / "tiny",
        "two": shared / "moglow" / "tiny",
        "own_files": own_files,
        "first": first,
        "resumed": resumed,
    }


def test_two_processes_see_two_devices(runs):
    for i, (_, out) in enumerate(runs["first"]):
        assert f"process {i} of 2, 2 devices in all" in out, out[-2000:]


def test_two_processes_reproduce_one_process_losses(runs):
    one, two = _losses(runs["one"]), _losses(runs["two"])
    assert sorted(one) == list(range(1, 7)) and sorted(two) == list(range(1, 7))
    steps = sorted(one)
    np.testing.assert_allclose([two[s] for s in steps], [one[s] for s in steps], rtol=1e-5)
    assert len({round(v, 3) for v in one.values()}) == len(one)  # no constant, vacuous loss


def test_each_process_feeds_its_own_slice_of_every_global_batch(runs):
    whole = _trace(runs["base"] / "trace_one", 0)
    p0, p1 = (_trace(runs["base"] / "trace_two", i) for i in range(2))
    assert sorted(p0) == sorted(p1) == [0, 1, 2, 3]
    for step in p0:
        assert p0[step] and p1[step]
        assert not set(p0[step]) & set(p1[step]), "a row of the global batch fed twice"
        assert not set(p0[step].values()) & set(p1[step].values()), "a window fed twice"
        assert {**p0[step], **p1[step]} == whole[step]  # together: exactly the global batch
    assert whole[0] != whole[1]  # every step draws a new batch


def test_only_process_zero_writes_the_run_directory(runs):
    assert runs["own_files"] == [], runs["own_files"]
    two = runs["two"]
    for name in ("config.json", "standardizer.json", "metrics.jsonl"):
        assert (two / name).is_file()
    rows = [json.loads(line) for line in (two / "metrics.jsonl").read_text().splitlines()]
    train_steps = [r["step"] for r in rows if "loss" in r]
    assert train_steps == sorted(set(train_steps)), "metrics rows written twice"


def test_checkpoint_written_and_resumed_by_both_processes(runs):
    assert (runs["two"] / "checkpoints" / "latest" / "4").is_dir()
    for _, out in runs["resumed"]:
        assert "at step 4" in out and "resumed" in out, out[-2000:]
    assert (runs["two"] / "checkpoints" / "latest" / "6").is_dir()


def _one_error_line(out: str) -> str:
    errors = [line for line in out.splitlines() if line.startswith("error:")]
    assert len(errors) == 1, out[-3000:]
    assert "Traceback" not in out and "Check failure" not in out, out[-3000:]
    return errors[0]


def test_different_configs_are_refused_with_one_line(tmp_path):
    results = _two_processes(
        [_train_cmd(tmp_path / "runs", 2), _train_cmd(tmp_path / "runs", 3)], tmp_path
    )
    for rc, out in results:
        assert rc == 2, out[-3000:]
        assert "different configs" in _one_error_line(out)
    assert not (tmp_path / "runs" / "moglow" / "tiny" / "checkpoints").exists()


def test_unreachable_coordinator_is_one_line_not_an_abort(tmp_path):
    env = _env(
        tmp_path,
        MOTIONFLOWS_COORDINATOR=f"127.0.0.1:{_free_port()}",  # nobody listens there
        MOTIONFLOWS_NUM_PROCESSES="2",
        MOTIONFLOWS_PROCESS_ID="1",
        MOTIONFLOWS_INIT_TIMEOUT="3",
    )
    [(rc, out)] = _launch([_train_cmd(tmp_path / "runs", 2)], [env])
    assert rc == 2, out[-3000:]
    line = _one_error_line(out)
    assert "could not reach the coordinator 127.0.0.1:" in line and "within 3 s" in line


# A data-parallel step whose buffers are large enough for XLA:CPU to run thunks on its
# thread pool; with the default pool (max(cores, devices) threads) its all-reduce waited
# for a device that had no thread left and aborted the process.
SIMULATED = textwrap.dedent(
    """
    from motionflows.distributed import configure_cpu_threads
    print("threads for 2 devices >= 4:", configure_cpu_threads() >= 4)
    import jax, jax.numpy as jnp, numpy as np
    from motionflows.sharding import batch_sharding, data_mesh, replicate

    mesh = data_mesh()
    assert len(mesh.devices.ravel()) == 2, mesh
    params = replicate({f"w{i}": jnp.full((64, 64), 0.01) for i in range(16)}, mesh)
    x = np.random.default_rng(0).normal(size=(16, 64)).astype(np.float32)
    x = jax.device_put(x, batch_sharding(mesh))

    @jax.jit
    def step(p, x):
        loss = lambda p: sum(jnp.mean(jnp.tanh(x @ w) ** 2) for w in p.values())
        value, grads = jax.value_and_grad(loss)(p)
        return jax.tree_util.tree_map(lambda a, g: a - 0.1 * g, p, grads), value

    for _ in range(300):
        params, value = step(params, x)
    print("OK", float(value))
    """
)


def test_simulated_devices_all_reduce_without_deadlock(tmp_path):
    # A short rendezvous timeout makes a deadlock fail in seconds instead of 40 s.
    flags = (
        "--xla_force_host_platform_device_count=2 "
        "--xla_cpu_collective_call_terminate_timeout_seconds=15"
    )
    env = _env(tmp_path, XLA_FLAGS=flags)
    for name in ("PJRT_NPROC", "NPROC", "JAX_DISABLE_MOST_OPTIMIZATIONS"):
        env.pop(name, None)
    [(rc, out)] = _launch([[sys.executable, "-c", SIMULATED]], [env])
    assert rc == 0, out[-3000:]
    assert "threads for 2 devices >= 4: True" in out and "OK" in out


def test_too_few_threads_for_simulated_devices_is_one_line(tmp_path):
    env = _env(tmp_path, XLA_FLAGS="--xla_force_host_platform_device_count=4", PJRT_NPROC="4")
    [(rc, out)] = _launch([_train_cmd(tmp_path / "runs", 1)], [env])
    assert rc == 2, out[-3000:]
    assert "PJRT_NPROC=8" in _one_error_line(out)


def test_cpu_devices_flag_trains_data_parallel(tmp_path):
    env = _env(tmp_path)
    for name in ("PJRT_NPROC", "NPROC"):
        env.pop(name, None)
    [(rc, out)] = _launch([_train_cmd(tmp_path / "runs", 2, "--cpu-devices", "2")], [env])
    assert rc == 0, out[-3000:]
    assert "data-parallel over 2 devices" in out
    assert (tmp_path / "runs" / "moglow" / "tiny" / "metrics.jsonl").exists()


def test_cpu_devices_flag_refuses_zero_with_one_line(tmp_path):
    [(rc, out)] = _launch(
        [_train_cmd(tmp_path / "runs", 2, "--cpu-devices", "0")], [_env(tmp_path)]
    )
    assert rc == 2, out[-3000:]
    assert "--cpu-devices must be 1 .. 256" in _one_error_line(out)


def test_simulate_cpu_devices_sets_the_count_and_keeps_other_flags(monkeypatch):
    from motionflows.distributed import check_cpu_devices, simulate_cpu_devices

    env = {"XLA_FLAGS": "--xla_force_host_platform_device_count=8 --xla_cpu_use_onednn=true"}
    simulate_cpu_devices(2, env)
    assert env["XLA_FLAGS"].split() == [
        "--xla_cpu_use_onednn=true",
        "--xla_force_host_platform_device_count=2",
    ]
    assert int(env["PJRT_NPROC"]) >= 4  # two threads per simulated device
    untouched: dict = {}
    simulate_cpu_devices(None, untouched)
    assert untouched == {}
    # this process's CPU backend has already started: a different count is refused
    import jax

    monkeypatch.setattr(jax, "default_backend", lambda: "cpu")  # as on a GPU machine too
    from motionflows.errors import RunError

    started = len(jax.local_devices(backend="cpu"))
    check_cpu_devices(started)
    with pytest.raises(RunError, match="new process"):
        check_cpu_devices(started + 1)


def test_cpu_devices_on_an_accelerator_warns_that_it_has_no_effect(monkeypatch):
    import jax

    from motionflows.distributed import check_cpu_devices

    monkeypatch.setattr(jax, "default_backend", lambda: "gpu")
    with pytest.warns(UserWarning, match="--cpu-devices 4 has no effect: JAX computes on gpu"):
        check_cpu_devices(4)


@pytest.mark.parametrize("value", ["0", "-5"])
def test_a_join_timeout_of_no_seconds_is_refused(monkeypatch, value):
    """MOTIONFLOWS_INIT_TIMEOUT=0 silently became 300 s, a negative one fired the watchdog
    at once (exit 2 with a misleading "not all joined")."""
    from motionflows.distributed import initialize
    from motionflows.errors import RunError

    monkeypatch.setenv("MOTIONFLOWS_INIT_TIMEOUT", value)
    with pytest.raises(RunError, match="MOTIONFLOWS_INIT_TIMEOUT must be a number of seconds"):
        initialize()
