"""Orbax's own noise while a checkpoint is read, kept from the user behind one-line errors.

:func:`quiet_orbax` keeps orbax and absl from logging their tracebacks while
:mod:`motionflows.checkpoints` turns a failure into one line.

:func:`drop_echoes_of` handles what a failed read leaves behind. When orbax's restore of a
damaged step fails on its first bad array, the reads it still has in flight finish on
tensorstore's threads after orbax has closed its event loop: each raises "Event loop is
closed" (reported through ``sys.unraisablehook``) or leaves an asyncio task whose
exception asyncio logs ("Task exception was never retrieved") when the task is collected.
Both reached the user as tracebacks, before or after the one-line error, in about half the
runs of ``motionflows sample`` on a damaged exported MoGlow. The failure is reported once
(``CheckpointReadError`` or the fallback warning), so from then on the process drops those
echoes; every other unraisable exception and asyncio record reaches the hooks that were
there before. An echo can also arrive before the failure is reported, while orbax is still
unwinding (an aborted read's task collected on the way out); so within :func:`quiet_orbax`
both kinds are held and passed on at the block's end, when the failed folder is known.
"""

from __future__ import annotations

import contextlib
import logging
import sys
from pathlib import Path

_DAMAGED: set[str] = set()
"""Checkpoint step folders that failed to restore in this process."""


def _is_echo(exc: BaseException | None, text: str) -> bool:
    """An aborted read's echo: "Event loop is closed" raised on a tensorstore thread, or
    an error whose text names a step folder that failed to restore."""
    if isinstance(exc, RuntimeError) and str(exc) == "Event loop is closed":
        return True
    return any(folder in text for folder in _DAMAGED)


_HELD: list[list] = []
"""One list per open :func:`quiet_orbax` block, innermost last: the asyncio records with an
exception and the unraisable exceptions that arrived in it, passed on at its end."""


def _install_unraisable_filter():
    """Wrap ``sys.unraisablehook`` (once) so that it drops echoes and, within a
    :func:`quiet_orbax` block, holds the rest; returns the undo."""
    previous = sys.unraisablehook
    if getattr(previous, "drops_echoes", False):
        return lambda: None

    def hook(unraisable) -> None:
        if _is_echo(unraisable.exc_value, f"{unraisable.exc_value} {unraisable.object!r}"):
            return
        if _HELD:
            _HELD[-1].append(unraisable)
        else:
            previous(unraisable)

    hook.drops_echoes = True
    sys.unraisablehook = hook
    return lambda: setattr(sys, "unraisablehook", previous)


class _DropEchoes(logging.Filter):
    """On the ``asyncio`` logger: drops the records of tasks that read a failed step."""

    def filter(self, record: logging.LogRecord) -> bool:
        exc = record.exc_info[1] if record.exc_info else None
        return exc is None or not _is_echo(exc, f"{record.getMessage()} {exc}")


class _Hold(logging.Filter):
    """On the ``asyncio`` logger while a :func:`quiet_orbax` block is open: holds the
    records that carry an exception in the innermost block's list."""

    def filter(self, record: logging.LogRecord) -> bool:
        if record.exc_info and _HELD:
            _HELD[-1].append(record)
            return False
        return True


_HOLD = _Hold()


@contextlib.contextmanager
def quiet_orbax():
    """Within the block: orbax and absl log nothing below CRITICAL; asyncio's records of
    exceptions and unraisable exceptions are held and, at the block's end, passed on unless
    they echo a step that failed in it (:func:`drop_echoes_of`). Once a step has failed,
    the echo filters stay for the rest of the process."""
    loggers = [logging.getLogger(n) for n in ("absl", "orbax")]
    levels = [lg.level for lg in loggers]
    for lg in loggers:
        lg.setLevel(logging.CRITICAL)
    undo = _install_unraisable_filter()
    asyncio_log = logging.getLogger("asyncio")
    _HELD.append([])
    asyncio_log.addFilter(_HOLD)  # once, however deeply blocks nest
    try:
        yield
    finally:
        held = _HELD.pop()
        if not _HELD:
            asyncio_log.removeFilter(_HOLD)
        for lg, level in zip(loggers, levels, strict=True):
            lg.setLevel(level)
        if not _DAMAGED:
            undo()
        for item in held:  # through the filters again: now they know the failed folders
            if isinstance(item, logging.LogRecord):
                asyncio_log.handle(item)
            else:
                sys.unraisablehook(item)


def drop_echoes_of(folder: Path) -> None:
    """``folder`` (a checkpoint step) failed to restore: from now on drop the echoes of
    its aborted reads (the module docstring)."""
    if not _DAMAGED:
        logging.getLogger("asyncio").addFilter(_DropEchoes())
    _DAMAGED.add(str(Path(folder).absolute()))
    _install_unraisable_filter()
