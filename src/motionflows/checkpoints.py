"""Orbax checkpoints of a run: the latest N steps plus the best by validation.

Layout: ``<run>/checkpoints/latest/<step>/`` (``keep`` most recent) and
``<run>/checkpoints/best/<step>/`` (one: the lowest validation NLL so far). Each holds
``state`` (the model's trainable ``params``, its other variables ``rest``, the optimiser
state ``opt``: every pytree stored as its flattened leaves, rebuilt against a freshly built
template) and ``meta`` (JSON: step, seed, RNG key data, data-iterator position, guard
counters, best validation NLL). A checkpoint never holds NaN or inf: :meth:`save` refuses.
"""

from __future__ import annotations

import contextlib
import logging
import sys
from pathlib import Path
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

logging.getLogger("absl").setLevel(logging.WARNING)


def _to_host(leaf: Any) -> np.ndarray:
    if isinstance(leaf, jax.Array) and not leaf.is_fully_addressable:
        if not leaf.sharding.is_fully_replicated:
            raise ValueError("only replicated (data-parallel) state can be checkpointed")
        leaf = leaf.addressable_data(0)  # multi-host: this process's full copy
    if isinstance(leaf, jax.Array) and jnp.issubdtype(leaf.dtype, jax.dtypes.prng_key):
        leaf = jax.random.key_data(leaf)
    return np.asarray(leaf)


def flatten(tree: Any) -> dict[str, np.ndarray]:
    """A pytree's leaves as ``{"000000": array, ...}`` (typed PRNG keys as key data)."""
    return {f"{i:06d}": _to_host(leaf) for i, leaf in enumerate(jax.tree_util.tree_leaves(tree))}


def unflatten(template: Any, flat: dict[str, Any], what: str = "state") -> Any:
    """Rebuild a pytree shaped like ``template`` from :func:`flatten` output."""
    leaves, treedef = jax.tree_util.tree_flatten(template)
    if len(leaves) != len(flat):
        raise ValueError(
            f"checkpoint {what} has {len(flat)} arrays but the model built from config.json "
            f"has {len(leaves)}: the code changed since the run was saved"
        )
    out = []
    for i, leaf in enumerate(leaves):
        value = np.asarray(flat[f"{i:06d}"])
        if tuple(value.shape) != tuple(np.shape(leaf)) and not (
            isinstance(leaf, jax.Array) and jnp.issubdtype(leaf.dtype, jax.dtypes.prng_key)
        ):
            raise ValueError(
                f"checkpoint {what} array {i} has shape {value.shape}, the model expects "
                f"{np.shape(leaf)}: the code or config changed since the run was saved"
            )
        if isinstance(leaf, jax.Array) and jnp.issubdtype(leaf.dtype, jax.dtypes.prng_key):
            out.append(jax.random.wrap_key_data(jnp.asarray(value)))
        else:
            out.append(jnp.asarray(value, dtype=getattr(leaf, "dtype", None)))
    return jax.tree_util.tree_unflatten(treedef, out)


class CheckpointReadError(ValueError):
    """No complete checkpoint could be read (each damaged step is named)."""


class CheckpointWriteError(OSError):
    """A checkpoint could not be written (a full disk, no permission); one line for people."""


def _os_error(err: BaseException) -> OSError | None:
    """The ``OSError`` behind ``err`` (through ``__cause__`` / ``__context__``), if any."""
    seen = set()
    while err is not None and id(err) not in seen:
        if isinstance(err, OSError):
            return err
        seen.add(id(err))
        err = err.__cause__ or err.__context__
    return None


@contextlib.contextmanager
def _quiet_orbax():
    """Keep orbax/absl from logging its own tracebacks while we turn errors into one line."""
    loggers = [logging.getLogger(n) for n in ("absl", "orbax")]
    levels = [lg.level for lg in loggers]
    for lg in loggers:
        lg.setLevel(logging.CRITICAL)
    try:
        yield
    finally:
        for lg, level in zip(loggers, levels, strict=True):
            lg.setLevel(level)


def all_finite(flat: dict[str, np.ndarray]) -> bool:
    """Whether every floating-point array is finite."""
    return all(np.all(np.isfinite(v)) for v in flat.values() if np.issubdtype(v.dtype, np.inexact))


class Checkpointer:
    """Latest-N plus best-by-validation orbax checkpoints under ``directory``."""

    def __init__(self, directory: str | Path, *, keep: int = 3):
        import orbax.checkpoint as ocp

        self._ocp = ocp
        self.directory = Path(directory)

        def manager(sub: str, n: int):
            opts = ocp.CheckpointManagerOptions(
                max_to_keep=n, create=True, enable_async_checkpointing=False
            )
            return ocp.CheckpointManager((self.directory / sub).absolute(), options=opts)

        with _quiet_orbax():  # a damaged step is reported by restore(), in one line
            self.managers = {
                "latest": manager("latest", max(1, keep)),
                "best": manager("best", 1),
            }

    def steps(self, which: str = "latest") -> list[int]:
        with _quiet_orbax():
            return list(self.managers[which].all_steps())

    def latest_step(self, which: str = "latest") -> int | None:
        with _quiet_orbax():
            return self.managers[which].latest_step()

    def save(self, step: int, state: dict[str, Any], meta: dict, *, which: str = "latest"):
        """Save ``state`` (dict of pytrees) and JSON ``meta`` at ``step``; refuses NaN/inf."""
        ocp = self._ocp
        flat = {name: flatten(tree) for name, tree in state.items()}
        for name, group in flat.items():
            if not all_finite(group):
                raise FloatingPointError(
                    f"refusing to checkpoint step {step}: the {name} hold NaN or inf"
                )
        mgr = self.managers[which]
        try:
            with _quiet_orbax():
                if step in mgr.all_steps():
                    mgr.delete(step)
                mgr.save(
                    step,
                    args=ocp.args.Composite(
                        state=ocp.args.StandardSave(flat), meta=ocp.args.JsonSave(dict(meta))
                    ),
                )
                mgr.wait_until_finished()
        except OSError as err:
            raise CheckpointWriteError(
                f"cannot write checkpoint step {step} to {self.directory / which}: "
                f"{err.strerror or err}; free disk space (or fix the folder's permissions) "
                "and continue with --resume from the last complete checkpoint"
            ) from None
        except Exception as err:  # orbax wraps I/O errors (e.g. a full disk) in its own types
            cause = _os_error(err)
            if cause is None:
                raise
            raise CheckpointWriteError(
                f"cannot write checkpoint step {step} to {self.directory / which}: "
                f"{cause.strerror or cause}; free disk space (or fix the folder's "
                "permissions) and continue with --resume from the last complete checkpoint"
            ) from None

    def restore(
        self, templates: dict[str, Any], *, which: str = "latest", step: int | None = None
    ) -> tuple[dict[str, Any], dict]:
        """Restore ``(state, meta)``; ``templates`` give each state entry's pytree shape."""
        ocp = self._ocp
        mgr = self.managers[which]
        # an explicit step must load; otherwise the newest complete checkpoint is used
        with _quiet_orbax():
            every = mgr.all_steps()
        candidates = sorted(every, reverse=True) if step is None else [step]
        if not candidates:
            raise FileNotFoundError(f"no {which} checkpoint in {self.directory}")
        args = ocp.args.Composite(state=ocp.args.StandardRestore(), meta=ocp.args.JsonRestore())
        got, damaged = None, []
        for candidate in candidates:
            try:
                with _quiet_orbax():
                    got = mgr.restore(candidate, args=args)
                break
            except Exception as err:  # a truncated or damaged step directory
                if step is not None:
                    raise CheckpointReadError(
                        f"checkpoint step {candidate} in {self.directory / which} cannot be "
                        f"read ({type(err).__name__}); it is damaged or incomplete"
                    ) from None
                damaged.append(candidate)
        if got is None:
            raise CheckpointReadError(
                f"no readable {which} checkpoint in {self.directory}: steps {damaged} are "
                "damaged or incomplete; train the run again (without --resume, into a new "
                "--run-name)"
            )
        if damaged:
            print(
                f"warning: {which} checkpoint step(s) {damaged} in {self.directory / which} "
                f"are damaged or incomplete; using step {candidate}, the newest complete one",
                file=sys.stderr,
            )
        flat = got["state"]
        state = {
            name: unflatten(template, flat.get(name, {}), name)
            for name, template in templates.items()
        }
        return state, dict(got["meta"])

    def close(self):
        for mgr in self.managers.values():
            mgr.close()
