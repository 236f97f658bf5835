"""The persistent compilation cache the ``motionflows`` command turns on."""

from __future__ import annotations

import os
import subprocess
import sys

PROBE = (
    "import jax; from motionflows.compile_cache import use_persistent_cache as u; "
    "print(u(), jax.config.jax_compilation_cache_dir)"
)


def _probe(tmp_path, **env):
    base = {k: v for k, v in os.environ.items() if k not in ("JAX_COMPILATION_CACHE_DIR",)}
    base.pop("MOTIONFLOWS_COMPILE_CACHE", None)
    base.update(XDG_CACHE_HOME=str(tmp_path / "xdg"), JAX_PLATFORMS="cpu", **env)
    out = subprocess.run(
        [sys.executable, "-c", PROBE], env=base, capture_output=True, text=True, check=True
    )
    return out.stdout.split()


def test_default_folder_is_under_the_user_cache(tmp_path):
    folder, configured = _probe(tmp_path)
    assert folder == configured == str(tmp_path / "xdg" / "motionflows" / "jax")
    assert (tmp_path / "xdg" / "motionflows" / "jax").is_dir()


def test_named_folder_and_off(tmp_path):
    folder, configured = _probe(tmp_path, MOTIONFLOWS_COMPILE_CACHE=str(tmp_path / "c"))
    assert folder == configured == str(tmp_path / "c")
    folder, configured = _probe(tmp_path, MOTIONFLOWS_COMPILE_CACHE="0")
    assert folder == configured == "None"
    assert not (tmp_path / "xdg").exists()


def test_the_users_jax_setting_wins(tmp_path):
    folder, configured = _probe(tmp_path, JAX_COMPILATION_CACHE_DIR=str(tmp_path / "mine"))
    assert folder == "None" and configured == str(tmp_path / "mine")


def test_the_cache_is_written_and_read_back_without_warnings(tmp_path):
    """A size limit on the cache (jax_compilation_cache_max_size, tried 2026-12-07) made every
    read of an entry fail with a warning without the ``filelock`` package, and with it every
    write into a cache written without the limit: the cache must work silently."""
    code = (
        "import jax, jax.numpy as jnp; from motionflows.compile_cache import use_persistent_cache"
        " as u; u(); print(float(jax.jit(lambda x: jnp.sin(x) * 3.0 + x)(1.0)))"
    )
    env = {k: v for k, v in os.environ.items() if k != "JAX_COMPILATION_CACHE_DIR"}
    env.update(MOTIONFLOWS_COMPILE_CACHE=str(tmp_path / "c"), JAX_PLATFORMS="cpu")
    for _ in range(2):  # the first run writes the entry, the second reads it
        out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True,
                             text=True, check=True)  # fmt: skip
        assert "cache" not in out.stderr.lower(), out.stderr
    assert any((tmp_path / "c").iterdir())
