"""Composable invertible maps of motion sequences (..., T, D), each a Flax NNX pytree.

Direction: ``forward`` = latent -> data (sampling), ``inverse`` = data -> latent
(likelihood); ``*_and_log_det`` also return log|det| of that direction with the batch shape.
``forward_step`` / ``inverse_step`` run one frame (..., D) with an explicit carry
(``initial_carry``), for autoregressive sampling, streaming and causal scoring.
See :mod:`motionflows.bijectors.base` for the interface and :func:`initialize_from_data`
for the explicit data-dependent initialisation.
"""

from motionflows.bijectors.actnorm import ActNorm, initialize_from_data
from motionflows.bijectors.base import (
    Bijector,
    Chain,
    Fixed,
    Inverse,
    MapContext,
    Scan,
    check_event,
    check_frame,
    data_init_mode,
    is_initializing,
)
from motionflows.bijectors.coupling import (
    AdditiveCoupling,
    AffineCoupling,
    affine_params,
    affine_to_data,
    affine_to_latent,
    coupling_sizes,
    merge_halves,
    split_halves,
)
from motionflows.bijectors.difference import Difference
from motionflows.bijectors.linear import DenseLinear, InvertibleLinear, Permute, Reverse
from motionflows.bijectors.reshape import Split, Squeeze, squeeze_time, unsqueeze_time

__all__ = [
    "ActNorm",
    "AdditiveCoupling",
    "AffineCoupling",
    "Bijector",
    "Chain",
    "DenseLinear",
    "Difference",
    "Fixed",
    "Inverse",
    "InvertibleLinear",
    "MapContext",
    "Permute",
    "Reverse",
    "Scan",
    "Split",
    "Squeeze",
    "affine_params",
    "affine_to_data",
    "affine_to_latent",
    "check_event",
    "check_frame",
    "coupling_sizes",
    "data_init_mode",
    "initialize_from_data",
    "is_initializing",
    "merge_halves",
    "split_halves",
    "squeeze_time",
    "unsqueeze_time",
]
