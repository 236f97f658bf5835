"""``motionflows bench``: train (or reuse) every model on one split and compare them honestly.

One command writes ``DIR/BENCHMARK.md``, ``DIR/results.json`` and plots::

    motionflows bench --data synthetic --budget quick --out runs/bench

The models are those of the experiments registered in the ``motionflows.experiments``
entry points (:mod:`motionflows.bench.budgets`); each experiment declares what the bench
needs: ``SCOPES`` (what its ``evaluate`` scores), ``CAUSAL`` (whether frame t depends on
frames < t only: per-frame NLL by prefixes), a ``smoke`` preset, and optionally
``BENCH_MODELS`` and ``window_log_prob``. What is compared, and how (every number names its
unit and scope):

* **Likelihood** on the test split (:mod:`~motionflows.bench.scoring`). Every model sees the
  *same* data configuration (one :class:`~motionflows.config.DataConfig` is forced onto every
  experiment's config), hence identical test windows x_1:T (metres) and controls c_1:T:
  NLL in nats/frame in metres and bits/frame standardised per scope, mean and a bootstrap
  95% interval, for the test split and (a deterministic subset of) the training split.
* **Motion quality** of samples drawn for the test controls at a stated temperature, with the
  metrics of ``motionflows.evaluation.motion``; the ground-truth test motion is scored the same
  way as a reference row.
* **Speed** (:mod:`~motionflows.bench.speed`): training frames/s (median over the run's
  ``metrics.jsonl``) and sampling frames/s at batch 1 and 64 (compile time excluded and
  reported separately), on the machine described.

Budgets: ``smoke`` = each experiment's ``smoke`` preset (a CI-sized model, a few steps),
``quick`` = the ``quick`` preset, ``cpu`` = the ``cpu`` preset, ``full`` = the ``paper``
preset. A finished run under ``runs/`` whose saved config equals the one the bench would
train is reused instead of retrained (:mod:`~motionflows.bench.reuse`). The report is
:mod:`~motionflows.bench.report` and :mod:`~motionflows.bench.plots`; the command line
:mod:`motionflows.cli_bench`.
"""

from motionflows.bench.benchmark import bench_model, render_gif, run_benchmark
from motionflows.bench.budgets import (
    BUDGET_NOTES,
    BUDGET_SIZES,
    BUDGETS,
    EVAL_CHUNK,
    SMOKE_DATA,
    BenchModel,
    all_models,
    bench_config,
    bench_models,
    check_overrides,
    load_experiment,
    parse_data_spec,
    parse_models,
)
from motionflows.bench.estimate import estimate_training
from motionflows.bench.report import MOTION_NOTE
from motionflows.bench.reuse import find_run, fit_seconds, obtain_run, run_finished, train_speed
from motionflows.bench.scoring import (
    DIVERGED_METRES,
    MOTION_METRICS,
    data_references,
    diverged,
    merge_splits,
    motion_metrics,
    natural_diversity_of,
    per_frame_nll,
    score_likelihood,
)
from motionflows.bench.speed import (
    count_params,
    describe_machine,
    make_sampler,
    sample_in_chunks,
    time_sampler,
)
from motionflows.windows import complete_windows

__all__ = [
    "ALL_MODELS",
    "BUDGETS",
    "BUDGET_NOTES",
    "BUDGET_SIZES",
    "DIVERGED_METRES",
    "EVAL_CHUNK",
    "MOTION_METRICS",
    "MOTION_NOTE",
    "SMOKE_DATA",
    "BenchModel",
    "all_models",
    "bench_config",
    "bench_model",
    "bench_models",
    "build_parser",
    "check_overrides",
    "complete_windows",
    "count_params",
    "data_references",
    "describe_machine",
    "diverged",
    "estimate_training",
    "find_run",
    "fit_seconds",
    "load_experiment",
    "main",
    "make_sampler",
    "merge_splits",
    "motion_metrics",
    "natural_diversity_of",
    "obtain_run",
    "parse_data_spec",
    "parse_models",
    "per_frame_nll",
    "render_gif",
    "run_benchmark",
    "run_finished",
    "sample_in_chunks",
    "score_likelihood",
    "time_sampler",
    "train_speed",
]


def __getattr__(name: str):
    # ALL_MODELS is read from the entry points when asked for (it imports every experiment);
    # the command line lives in motionflows.cli_bench and stays reachable from here
    if name == "ALL_MODELS":
        return all_models()
    if name in ("main", "build_parser"):
        from motionflows import cli_bench

        return getattr(cli_bench, name)
    if name == "draw_samples":  # renamed: motionflows.run.draw_samples is the other sampler
        import warnings

        warnings.warn(
            "motionflows.bench.draw_samples is deprecated, use bench.sample_in_chunks (same "
            "contract)",
            DeprecationWarning,
            stacklevel=2,
        )
        return sample_in_chunks
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
