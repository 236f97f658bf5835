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
there before.
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


def _install_unraisable_filter():
    """Wrap ``sys.unraisablehook`` (once) so that it drops echoes; returns the undo."""
    previous = sys.unraisablehook
    if getattr(previous, "drops_echoes", False):
        return lambda: None

    def hook(unraisable) -> None:
        if not _is_echo(unraisable.exc_value, f"{unraisable.exc_value} {unraisable.object!r}"):
            previous(unraisable)

    hook.drops_echoes = True
    sys.unraisablehook = hook
    return lambda: setattr(sys, "unraisablehook", previous)


class _DropEchoes(logging.Filter):
    """On the ``asyncio`` logger: drops the records of tasks that read a failed step."""

    def filter(self, record: logging.LogRecord) -> bool:
        exc = record.exc_info[1] if record.exc_info else None
        return exc is None or not _is_echo(exc, f"{record.getMessage()} {exc}")


@contextlib.contextmanager
def quiet_orbax():
    """Within the block: orbax and absl log nothing below CRITICAL, and echoes of aborted
    reads that arrive while orbax is still unwinding are dropped. Once a step has failed
    (:func:`drop_echoes_of`), the echo filter stays for the rest of the process."""
    loggers = [logging.getLogger(n) for n in ("absl", "orbax")]
    levels = [lg.level for lg in loggers]
    for lg in loggers:
        lg.setLevel(logging.CRITICAL)
    undo = _install_unraisable_filter()
    try:
        yield
    finally:
        for lg, level in zip(loggers, levels, strict=True):
            lg.setLevel(level)
        if not _DAMAGED:
            undo()


def drop_echoes_of(folder: Path) -> None:
    """``folder`` (a checkpoint step) failed to restore: from now on drop the echoes of
    its aborted reads (the module docstring)."""
    if not _DAMAGED:
        logging.getLogger("asyncio").addFilter(_DropEchoes())
    _DAMAGED.add(str(Path(folder).absolute()))
    _install_unraisable_filter()
