"""The benchmark's report, now :mod:`motionflows.bench.report` (tables, ``BENCHMARK.md``) and
:mod:`motionflows.bench.plots`; this module keeps the old import path working."""

from motionflows.bench.plots import plot_metric_bars, plot_per_frame_nll
from motionflows.bench.report import (
    LIKELIHOOD_HEADER,
    likelihood_rows,
    motion_table,
    performer_table,
    speed_table,
    write_markdown,
)

__all__ = [
    "LIKELIHOOD_HEADER",
    "likelihood_rows",
    "motion_table",
    "performer_table",
    "plot_metric_bars",
    "plot_per_frame_nll",
    "speed_table",
    "write_markdown",
]
