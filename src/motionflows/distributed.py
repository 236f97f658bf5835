"""Several processes and simulated devices: joining a run, thread pools, config agreement.

Data parallelism itself lives in :mod:`motionflows.sharding` (one ``data`` mesh axis);
this module holds what is per process:

* :func:`initialize` joins a multi-process run through ``jax.distributed.initialize`` from
  the environment variables below, and turns the failures that would otherwise abort in
  native code (a coordinator that cannot be reached, processes that never join) into one
  :class:`~motionflows.errors.RunError` line;
* :func:`simulate_cpu_devices` (the CLI's ``--cpu-devices N``) splits the CPU into N
  simulated XLA devices, :func:`check_cpu_devices` confirms JAX started with them;
* :func:`configure_cpu_threads` sizes XLA:CPU's thread pool for simulated devices
  (``--xla_force_host_platform_device_count=N``) so that their all-reduce cannot deadlock;
* :func:`check_same_config` refuses to train when the processes were given different
  configs;
* :func:`trace_local_rows` records which windows of each global batch this process fed
  (a test hook, on when ``MOTIONFLOWS_TRACE_BATCHES`` names a folder).

Environment:

``MOTIONFLOWS_COORDINATOR``   ``host:port`` of process 0, which runs JAX's coordinator
``MOTIONFLOWS_NUM_PROCESSES`` the number of processes N
``MOTIONFLOWS_PROCESS_ID``    this process, 0 .. N-1
``MOTIONFLOWS_INIT_TIMEOUT``  seconds to wait for all N processes to join (default 300)
"""

from __future__ import annotations

import hashlib
import json
import os
import re
import sys
import threading
import warnings
from pathlib import Path
from typing import Any

import jax
import numpy as np

from motionflows.errors import RunError

COORDINATOR = "MOTIONFLOWS_COORDINATOR"
NUM_PROCESSES = "MOTIONFLOWS_NUM_PROCESSES"
PROCESS_ID = "MOTIONFLOWS_PROCESS_ID"
INIT_TIMEOUT = "MOTIONFLOWS_INIT_TIMEOUT"
TRACE_BATCHES = "MOTIONFLOWS_TRACE_BATCHES"

_DEVICE_COUNT_FLAG = re.compile(r"--xla_force_host_platform_device_count=(\d+)")


# ------------------------------------------------------------------ simulated CPU devices


def simulated_device_count(xla_flags: str | None = None) -> int:
    """N of ``--xla_force_host_platform_device_count=N`` in ``xla_flags`` (default: the
    ``XLA_FLAGS`` environment variable); 1 when it is absent."""
    flags = os.environ.get("XLA_FLAGS", "") if xla_flags is None else xla_flags
    found = _DEVICE_COUNT_FLAG.findall(flags)
    return int(found[-1]) if found else 1


MAX_CPU_DEVICES = 256
"""The most simulated CPU devices ``--cpu-devices`` starts (100 000 hung the backend's
start for minutes; a useful count is about the number of cores)."""


def simulate_cpu_devices(n: int | None, environ: dict | None = None) -> None:
    """``--cpu-devices N``: run JAX's CPU backend as N simulated devices.

    Sets ``--xla_force_host_platform_device_count=N`` in ``XLA_FLAGS`` (replacing a count
    given there; other flags are kept), then sizes the thread pool
    (:func:`configure_cpu_threads`). XLA reads both when JAX starts its CPU backend, so
    this must run before the first JAX computation; :func:`check_cpu_devices` afterwards
    says so if it came too late. The trainer is data-parallel over all devices, so each
    device trains on batch / N windows with its own threads: on a 2-core CPU this runs
    the small models' time loops side by side (docs/readme/speed.md). None: nothing.
    """
    if n is None:
        return
    if not 1 <= n <= MAX_CPU_DEVICES:
        raise RunError(
            f"--cpu-devices must be 1 .. {MAX_CPU_DEVICES} (each device trains a share of "
            f"the batch on its own threads), got {n}"
        )
    env = os.environ if environ is None else environ
    flags = _DEVICE_COUNT_FLAG.sub("", env.get("XLA_FLAGS", "")).split()
    env["XLA_FLAGS"] = " ".join([*flags, f"--xla_force_host_platform_device_count={n}"])
    configure_cpu_threads(env)


def check_cpu_devices(n: int | None) -> None:
    """Refuse to go on when ``--cpu-devices n`` did not take effect (JAX's CPU backend had
    already started in this process with another device count); warn when JAX computes on
    an accelerator, where the simulated CPU devices stay unused."""
    if n is None:
        return
    if jax.default_backend() != "cpu":
        warnings.warn(
            f"--cpu-devices {n} has no effect: JAX computes on {jax.default_backend()} "
            f"({jax.device_count()} device(s)), not on the CPU",
            stacklevel=2,
        )
        return
    got = len(jax.local_devices(backend="cpu"))
    if got != n:
        raise RunError(
            f"--cpu-devices {n} came after JAX had started its CPU backend with {got} "
            f"device(s) in this process: run the command in a new process, or set "
            f"XLA_FLAGS=--xla_force_host_platform_device_count={n} before JAX is imported"
        )


def configure_cpu_threads(environ: dict | None = None) -> int | None:
    """Give XLA:CPU at least two threads per simulated device; returns the pool size set.

    Why: XLA:CPU runs every device's part of a program from one shared thread pool of
    ``max(PJRT_NPROC or cores, N)`` threads. At an all-reduce each device holds one thread
    (the launch, waiting for its program) and blocks a second one inside the collective
    until all N devices have arrived. With N threads only N - 1 devices get there, and
    after 40 s the rendezvous aborts the process (SIGABRT). Two threads per device is what
    one collective at a time needs (XLA:CPU launches one at a time); a longer rendezvous
    timeout would only wait longer for a device that cannot come.

    Sets ``PJRT_NPROC`` (read by XLA when JAX creates its CPU backend, so this must run
    before the first JAX computation) to ``max(2 N, cores)`` when N > 1 and neither
    ``PJRT_NPROC`` nor ``NPROC`` is set; a smaller value set by hand is refused with a
    :class:`RunError`. Returns None when nothing was needed.
    """
    env = os.environ if environ is None else environ
    n = simulated_device_count(env.get("XLA_FLAGS", ""))
    if n <= 1:
        return None
    need = 2 * n
    for name in ("PJRT_NPROC", "NPROC"):  # XLA reads the first one that is set
        if env.get(name):
            try:
                given = int(env[name])
            except ValueError:
                raise RunError(f"{name}={env[name]!r} is not a whole number") from None
            if given < need:
                raise RunError(
                    f"{name}={given} gives XLA:CPU too few threads for {n} simulated devices "
                    f"(their all-reduce would deadlock): set {name}={need} or more, or unset it"
                )
            return given
    size = max(need, os.cpu_count() or 1)
    env["PJRT_NPROC"] = str(size)
    return size


# ------------------------------------------------------------------------- joining a run


def _int_env(env: dict, name: str) -> int | None:
    text = env.get(name)
    if not text:
        return None
    try:
        return int(text)
    except ValueError:
        raise RunError(f"{name}={text!r} is not a whole number") from None


def _cluster_launch(env: dict) -> bool:
    """Whether a cluster launcher started several tasks that JAX can detect by itself
    (``srun --ntasks=N``, ``mpirun -n N``, Cloud TPU pods); a lone task inside a SLURM
    allocation (``salloc``, ``sbatch`` without ``srun``) stays single-process."""
    tasks = env.get("SLURM_STEP_NUM_TASKS") or env.get("SLURM_NTASKS")
    if "SLURM_PROCID" in env and tasks and tasks.isdigit() and int(tasks) > 1:
        return True
    size = env.get("OMPI_COMM_WORLD_SIZE", "")
    return (size.isdigit() and int(size) > 1) or "," in env.get("TPU_WORKER_HOSTNAMES", "")


def initialize(
    coordinator_address: str | None = None,
    num_processes: int | None = None,
    process_id: int | None = None,
    *,
    timeout_s: int | None = None,
) -> bool:
    """Join a multi-process run via ``jax.distributed.initialize``; returns whether it did.

    Arguments default to ``MOTIONFLOWS_COORDINATOR``, ``MOTIONFLOWS_NUM_PROCESSES``,
    ``MOTIONFLOWS_PROCESS_ID`` and ``MOTIONFLOWS_INIT_TIMEOUT``. Without a coordinator
    the run stays single-process unless a cluster launcher started several tasks (see
    :func:`_cluster_launch`), whose layout JAX then reads itself. Raises :class:`RunError`
    for incomplete or inconsistent settings; if the N processes have not all joined within
    the timeout, prints one ``error:`` line and exits with code 2 (JAX itself would abort
    in native code).
    """
    env = os.environ
    coordinator_address = coordinator_address or env.get(COORDINATOR) or None
    num_processes = num_processes if num_processes is not None else _int_env(env, NUM_PROCESSES)
    process_id = process_id if process_id is not None else _int_env(env, PROCESS_ID)
    if timeout_s is None:
        timeout_s = _int_env(env, INIT_TIMEOUT)
        timeout_s = 300 if timeout_s is None else timeout_s
    if timeout_s <= 0:
        raise RunError(f"{INIT_TIMEOUT} must be a number of seconds > 0, got {timeout_s}")
    if coordinator_address is None:
        if num_processes is not None or process_id is not None:
            raise RunError(
                f"{NUM_PROCESSES} / {PROCESS_ID} are set but {COORDINATOR} is not: set it to "
                "host:port of process 0 on every process"
            )
        if not _cluster_launch(env):
            return False
        what = "the cluster's processes"
    else:
        if num_processes is None or process_id is None:
            raise RunError(
                f"{COORDINATOR}={coordinator_address} also needs {NUM_PROCESSES} (N) and "
                f"{PROCESS_ID} (0 .. N-1) on every process"
            )
        if ":" not in coordinator_address:
            raise RunError(f"{COORDINATOR}={coordinator_address!r} must be host:port")
        if not 0 <= process_id < num_processes:
            raise RunError(
                f"{PROCESS_ID}={process_id} must be in 0 .. {num_processes - 1} "
                f"({NUM_PROCESSES}={num_processes})"
            )
        what = (
            f"process {process_id} of {num_processes} could not reach the coordinator "
            f"{coordinator_address} ({COORDINATOR}), or not all processes started"
            if process_id
            else f"the other {num_processes - 1} process(es) did not join the coordinator "
            f"{coordinator_address}"
        )
    with _Watchdog(
        timeout_s,
        f"error: {what} within {timeout_s} s; start all of them with the same "
        f"{COORDINATOR}, check that process 0's host and port are reachable, or raise "
        f"{INIT_TIMEOUT}",
    ):
        jax.distributed.initialize(
            coordinator_address=coordinator_address,
            num_processes=num_processes,
            process_id=process_id,
            initialization_timeout=timeout_s + 60,  # the watchdog speaks first
        )
    return True


class _Watchdog:
    """Print ``message`` and exit with code 2 unless the ``with`` block ends in time.

    ``jax.distributed.initialize`` cannot be interrupted from Python and aborts the
    process in native code when its own timeout passes, so a timer thread (the call
    releases the GIL while it waits) reports first and ends the process."""

    def __init__(self, seconds: float, message: str):
        self._timer = threading.Timer(seconds, self._fire, args=(message,))
        self._timer.daemon = True

    @staticmethod
    def _fire(message: str) -> None:
        print(message, file=sys.stderr, flush=True)
        os._exit(2)

    def __enter__(self):
        self._timer.start()
        return self

    def __exit__(self, *exc):
        self._timer.cancel()
        return False


# ------------------------------------------------------------------- consistency checks


def config_digest(experiment: str, config: Any) -> str:
    """SHA-256 (hex) of the experiment name and the config's JSON form."""
    from motionflows import config as cfg

    text = json.dumps({"experiment": experiment, "config": cfg.to_dict(config)}, sort_keys=True)
    return hashlib.sha256(text.encode()).hexdigest()


def check_same_config(experiment: str, config: Any) -> None:
    """Raise :class:`RunError` on every process unless all processes hold the same
    experiment and config (one all-gather of a digest; nothing happens in one process)."""
    if jax.process_count() == 1:
        return
    from jax.experimental import multihost_utils

    mine = np.frombuffer(bytes.fromhex(config_digest(experiment, config))[:16], np.uint32)
    every = np.asarray(multihost_utils.process_allgather(mine)).reshape(jax.process_count(), -1)
    differ = [i for i in range(len(every)) if not np.array_equal(every[i], every[0])]
    if differ:
        raise RunError(
            f"the {len(every)} processes were started with different configs (process "
            f"{', '.join(map(str, differ))} differ from process 0): give every process the "
            "same experiment, --preset, --data, --steps and --set flags"
        )


# ----------------------------------------------------------------------------- test hook


def trace_local_rows(step: int, batch: dict[str, jax.Array]) -> None:
    """Append the windows of ``batch["pose"]`` fed by this process's devices at ``step``
    to ``$MOTIONFLOWS_TRACE_BATCHES/process<i>.jsonl`` (nothing when it is unset).

    One JSON line per step: ``{"step", "process", "rows": {global row: fingerprint}}``,
    the fingerprint being the first 16 hex digits of the SHA-1 of the row's float32 bytes.
    """
    folder = os.environ.get(TRACE_BATCHES)
    if not folder:
        return
    rows = {}
    for shard in batch["pose"].addressable_shards:
        if shard.replica_id:
            continue
        start = shard.index[0].start or 0
        for i, row in enumerate(np.asarray(shard.data)):
            rows[start + i] = hashlib.sha1(np.ascontiguousarray(row).tobytes()).hexdigest()[:16]
    line = {"step": step, "process": jax.process_index(), "rows": rows}
    path = Path(folder) / f"process{jax.process_index()}.jsonl"
    path.parent.mkdir(parents=True, exist_ok=True)
    with path.open("a") as f:
        f.write(json.dumps(line) + "\n")
