"""Orbax checkpoints of a run: the latest N steps plus the best by validation.

Layout: ``<run>/checkpoints/latest/<step>/`` (``keep`` most recent) and
``<run>/checkpoints/best/<step>/`` (one: the lowest validation NLL so far). Each holds
``state`` (the model's trainable ``params``, its other variables ``rest``, the optimiser
state ``opt``) and ``meta`` (JSON: step, seed, RNG key data, data-iterator position, guard
counters, best validation NLL). A checkpoint never holds NaN or inf: :meth:`save` refuses.

``state`` is self-describing: a nested dict keyed by each array's pytree path, for a model
the NNX state path (``params/flows/0/steps/bijectors/2/logs``; optimiser state
``opt/0/mu/flows/...``), so orbax alone lists and loads it::

    import orbax.checkpoint as ocp
    state = ocp.StandardCheckpointer().restore(f"{run}/checkpoints/best/{step}/state")
    state["params"]["flows"]["0"]["steps"]["bijectors"]["2"]["logs"]  # (K, 2 D), numpy

Checkpoints written before this layout stored each pytree as its positional leaves
(``{"000000": array, ...}``, :func:`flatten`); :meth:`Checkpointer.restore` still reads
them (by position against the template, :func:`unflatten`).
"""

from __future__ import annotations

import logging
import re
import sys
from pathlib import Path
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from motionflows.checkpoint_noise import drop_echoes_of, quiet_orbax

logging.getLogger("absl").setLevel(logging.WARNING)


def _to_host(leaf: Any) -> np.ndarray:
    if isinstance(leaf, jax.Array) and not leaf.is_fully_addressable:
        if not leaf.sharding.is_fully_replicated:
            raise ValueError("only replicated (data-parallel) state can be checkpointed")
        leaf = leaf.addressable_data(0)  # multi-host: this process's full copy
    if isinstance(leaf, jax.Array) and jnp.issubdtype(leaf.dtype, jax.dtypes.prng_key):
        leaf = jax.random.key_data(leaf)
    return np.asarray(leaf)


def _is_key(leaf: Any) -> bool:
    return isinstance(leaf, jax.Array) and jnp.issubdtype(leaf.dtype, jax.dtypes.prng_key)


def _from_host(value: Any, leaf: Any) -> Any:
    """A stored array as the template leaf's type: typed PRNG keys re-wrapped, same dtype."""
    if _is_key(leaf):
        return jax.random.wrap_key_data(jnp.asarray(value))
    return jnp.asarray(value, dtype=getattr(leaf, "dtype", None))


# ----------------------------------------------------------------- the named layout


def _entry(key: Any) -> str:
    for attr in ("key", "idx", "name"):  # DictKey / FlattenedIndexKey, SequenceKey, GetAttrKey
        if hasattr(key, attr):
            return str(getattr(key, attr))
    return str(key)


def leaf_path(path: tuple) -> tuple[str, ...]:
    """A jax key path as strings; an NNX Variable's trailing ``.value`` is left out, so a
    parameter's name is its NNX state path (``("flows", "0", "steps", ..., "logs")``)."""
    if path and isinstance(path[-1], jax.tree_util.GetAttrKey) and path[-1].name == "value":
        path = path[:-1]
    return tuple(_entry(k) for k in path)


def named_leaves(tree: Any) -> dict[str, np.ndarray]:
    """A pytree's leaves on the host keyed by their ``/``-joined paths (typed PRNG keys as
    key data): ``{"flows/0/steps/bijectors/2/logs": array, ...}``."""
    out = {}
    for path, leaf in jax.tree_util.tree_flatten_with_path(tree)[0]:
        name = "/".join(leaf_path(path))
        if name in out:
            raise ValueError(f"two arrays of the state share the path {name!r}")
        out[name] = _to_host(leaf)
    return out


def nest(named: dict[str, np.ndarray]) -> dict[str, Any]:
    """``{"a/b": x}`` -> ``{"a": {"b": x}}``: the tree orbax stores (and lists by name)."""
    root: dict[str, Any] = {}
    for name, value in named.items():
        *parents, last = name.split("/")
        node = root
        for part in parents:
            node = node.setdefault(part, {})
            if not isinstance(node, dict):
                raise ValueError(f"state path {name!r} runs through an array")
        if last in node:
            raise ValueError(f"state path {name!r} is both an array and a folder")
        node[last] = value
    return root


def unnest(tree: Any, prefix: str = "") -> dict[str, Any]:
    """The inverse of :func:`nest`: a restored nested dict -> ``{"a/b": array}``."""
    if not isinstance(tree, dict):
        return {prefix: tree}
    out: dict[str, Any] = {}
    for key, value in tree.items():
        out.update(unnest(value, f"{prefix}/{key}" if prefix else str(key)))
    return out


def restore_named(template: Any, named: dict[str, Any], what: str = "state") -> Any:
    """Rebuild a pytree shaped like ``template`` from ``{path: array}`` (:func:`named_leaves`).

    Every template leaf is looked up by its path; a missing, extra or reshaped array raises
    one ``ValueError`` naming the first few paths.
    """
    pairs, treedef = jax.tree_util.tree_flatten_with_path(template)
    names = ["/".join(leaf_path(path)) for path, _ in pairs]
    missing = [n for n in names if n not in named]
    extra = sorted(set(named) - set(names))
    if missing or extra:
        raise ValueError(
            f"checkpoint {what} does not match the model built from config.json: "
            f"{len(missing)} array(s) missing (e.g. {missing[:3]}), {len(extra)} unexpected "
            f"(e.g. {extra[:3]}): the code changed since the run was saved"
        )
    out = []
    for name, (_, leaf) in zip(names, pairs, strict=True):
        value = np.asarray(named[name])
        if not _is_key(leaf) and tuple(value.shape) != tuple(np.shape(leaf)):
            raise ValueError(
                f"checkpoint {what} array {name!r} has shape {value.shape}, the model expects "
                f"{np.shape(leaf)}: the code or config changed since the run was saved"
            )
        out.append(_from_host(value, leaf))
    return jax.tree_util.tree_unflatten(treedef, out)


# ----------------------------------------------------- the positional layout (before)

_POSITIONAL = re.compile(r"\d{6}")


def is_positional(group: Any) -> bool:
    """Whether a restored state entry is in the layout of checkpoints written before the
    named one: a flat dict of arrays keyed ``"000000"``, ``"000001"``, ...."""
    return (
        isinstance(group, dict)
        and bool(group)
        and all(_POSITIONAL.fullmatch(str(k)) and not isinstance(v, dict) for k, v in group.items())
    )


def flatten(tree: Any) -> dict[str, np.ndarray]:
    """A pytree's leaves as ``{"000000": array, ...}`` (typed PRNG keys as key data): the
    positional layout of checkpoints written before the named one (read by
    :func:`unflatten`)."""
    return {f"{i:06d}": _to_host(leaf) for i, leaf in enumerate(jax.tree_util.tree_leaves(tree))}


def unflatten(template: Any, flat: dict[str, Any], what: str = "state") -> Any:
    """Rebuild a pytree shaped like ``template`` from :func:`flatten` output (by position)."""
    leaves, treedef = jax.tree_util.tree_flatten(template)
    if len(leaves) != len(flat):
        raise ValueError(
            f"checkpoint {what} has {len(flat)} arrays but the model built from config.json "
            f"has {len(leaves)}: the code changed since the run was saved"
        )
    out = []
    for i, leaf in enumerate(leaves):
        value = np.asarray(flat[f"{i:06d}"])
        if tuple(value.shape) != tuple(np.shape(leaf)) and not _is_key(leaf):
            raise ValueError(
                f"checkpoint {what} array {i} has shape {value.shape}, the model expects "
                f"{np.shape(leaf)}: the code or config changed since the run was saved"
            )
        out.append(_from_host(value, leaf))
    return jax.tree_util.tree_unflatten(treedef, out)


def restore_tree(template: Any, group: Any, what: str = "state") -> Any:
    """One restored state entry (either layout) as a pytree shaped like ``template``."""
    if is_positional(group):
        return unflatten(template, group, what)
    return restore_named(template, unnest(group or {}), what)


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


def all_finite(tree: Any) -> bool:
    """Whether every floating-point array of ``tree`` (e.g. :func:`named_leaves` output) is
    finite."""
    return all(
        np.all(np.isfinite(v))
        for v in jax.tree_util.tree_leaves(tree)
        if np.issubdtype(np.asarray(v).dtype, np.inexact)
    )


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

        with quiet_orbax():  # a damaged step is reported by restore(), in one line
            self.managers = {
                "latest": manager("latest", max(1, keep)),
                "best": manager("best", 1),
            }

    def steps(self, which: str = "latest") -> list[int]:
        with quiet_orbax():
            return list(self.managers[which].all_steps())

    def latest_step(self, which: str = "latest") -> int | None:
        with quiet_orbax():
            return self.managers[which].latest_step()

    def drop_after(self, step: int, which: str = "latest") -> list[int]:
        """Delete the ``which`` steps newer than ``step`` and return them: a run resumed at
        ``step`` replaces what came after it (damaged steps the restore skipped, a best
        validated on the abandoned trajectory), and orbax saves no step older than its
        newest."""
        mgr = self.managers[which]
        with quiet_orbax():
            newer = sorted(s for s in mgr.all_steps() if s > step)
            for s in newer:
                mgr.delete(s)
        if newer:
            print(
                f"removed {which} checkpoint step(s) {newer} in {self.directory / which}: "
                f"the run continues from step {step}",
                file=sys.stderr,
            )
        return newer

    def save(self, step: int, state: dict[str, Any], meta: dict, *, which: str = "latest"):
        """Save ``state`` (dict of pytrees) and JSON ``meta`` at ``step``; refuses NaN/inf.

        Each pytree is stored by name (see the module docstring)."""
        ocp = self._ocp
        named = {name: named_leaves(tree) for name, tree in state.items()}
        for name, group in named.items():
            if not all_finite(group):
                raise FloatingPointError(
                    f"refusing to checkpoint step {step}: the {name} hold NaN or inf"
                )
        stored = {name: nest(group) for name, group in named.items()}
        mgr = self.managers[which]
        try:
            with quiet_orbax():
                if step in mgr.all_steps():
                    mgr.delete(step)
                saved = mgr.save(
                    step,
                    args=ocp.args.Composite(
                        state=ocp.args.StandardSave(stored), meta=ocp.args.JsonSave(dict(meta))
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
        if not saved:  # orbax saves no step older than its newest, and says so with False
            raise CheckpointWriteError(
                f"checkpoint step {step} was not written to {self.directory / which}: it "
                f"holds a newer step ({self.latest_step(which)}); remove the newer steps or "
                "train into a new --run-name"
            )

    def restore(
        self, templates: dict[str, Any], *, which: str = "latest", step: int | None = None
    ) -> tuple[dict[str, Any], dict]:
        """Restore ``(state, meta)``; ``templates`` give each state entry's pytree shape.

        Reads both layouts: named (this version) and positional (checkpoints written
        before); a checkpoint that matches neither the template raises one ``ValueError``.
        """
        ocp = self._ocp
        mgr = self.managers[which]
        # an explicit step must load; otherwise the newest complete checkpoint is used
        with quiet_orbax():
            every = mgr.all_steps()
        candidates = sorted(every, reverse=True) if step is None else [step]
        if not candidates:
            raise FileNotFoundError(f"no {which} checkpoint in {self.directory}")
        args = ocp.args.Composite(state=ocp.args.StandardRestore(), meta=ocp.args.JsonRestore())
        got, damaged = None, []
        with quiet_orbax():  # also while a failed restore unwinds (checkpoint_noise)
            for candidate in candidates:
                try:
                    got = mgr.restore(candidate, args=args)
                    break
                except Exception as err:  # a truncated or damaged step directory
                    drop_echoes_of(mgr.directory / str(candidate))
                    if step is not None:
                        raise CheckpointReadError(
                            f"checkpoint step {candidate} in {self.directory / which} cannot "
                            f"be read ({type(err).__name__}); it is damaged or incomplete"
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
        stored = got["state"]
        state = {
            name: restore_tree(template, stored.get(name, {}), name)
            for name, template in templates.items()
        }
        return state, dict(got["meta"])

    def close(self):
        for mgr in self.managers.values():
            mgr.close()
