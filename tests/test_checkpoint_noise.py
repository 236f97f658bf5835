"""The echoes of a damaged checkpoint's aborted reads are dropped even when they arrive
before the failure is reported (while orbax is still unwinding); everything else passes."""

import logging
import sys
import types

from motionflows.checkpoint_noise import drop_echoes_of, quiet_orbax


class _Keep(logging.Handler):
    def __init__(self):
        super().__init__()
        self.records = []

    def emit(self, record):
        self.records.append(record)


def _task_error(text: str) -> logging.LogRecord:
    """A record as asyncio logs an uncollected task's exception."""
    try:
        raise ValueError(text)
    except ValueError:
        info = sys.exc_info()
    return logging.LogRecord(
        "asyncio", logging.ERROR, __file__, 1, "Task exception was never retrieved", (), info
    )


def test_echoes_that_arrive_before_the_failure_is_reported_are_dropped(tmp_path, monkeypatch):
    folder = tmp_path / "checkpoints" / "latest" / "7000"
    logger = logging.getLogger("asyncio")
    keep = _Keep()
    logger.addHandler(keep)
    seen = []
    monkeypatch.setattr(sys, "unraisablehook", seen.append)

    def unraisable(text):
        return types.SimpleNamespace(exc_value=OSError(text), object=None)

    try:
        with quiet_orbax():
            # collected while the restore unwinds: the folder is not known to be damaged yet
            logger.handle(_task_error(f"OUT_OF_RANGE reading {folder}/d/abc"))
            sys.unraisablehook(unraisable(f"read of {folder}/d/abc aborted"))
            logger.handle(_task_error("an unrelated task failed"))
            sys.unraisablehook(unraisable("an unrelated object failed"))
            drop_echoes_of(folder)  # the restore's except clause
            assert keep.records == [] and seen == [], "held until the block ends"
        # after the failure: echoes of that folder still dropped, the rest still passes
        logger.handle(_task_error(f"late read of {folder}/d/def"))
    finally:
        logger.removeHandler(keep)
    assert [r.exc_info[1].args[0] for r in keep.records] == ["an unrelated task failed"]
    assert [str(u.exc_value) for u in seen] == ["an unrelated object failed"]
