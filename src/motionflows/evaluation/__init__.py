"""Evaluation: likelihood tables (``likelihood``) and motion metrics (``motion``)."""

from motionflows.evaluation.likelihood import (
    bits_per_frame_standardized,
    bootstrap_ci,
    format_table,
    likelihood_rows,
    nats_per_frame_metres,
)

__all__ = [
    "bits_per_frame_standardized",
    "bootstrap_ci",
    "format_table",
    "likelihood_rows",
    "nats_per_frame_metres",
]
