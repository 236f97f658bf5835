"""Copies of a model laid out for sampling and streaming: :func:`inference_copy`.

Training wants the K flow steps' parameters stacked on a leading K axis (one ``lax.scan``
over the steps: compile time independent of K, one large product per step). Frame-by-frame
sampling wants them apart: inside the scan, step k's weights are ``W[k]``, a dynamic slice,
and XLA:CPU materialises every dynamic slice of a weight before the product reads it. So a
stacked MoGlow frame reads each weight, writes a copy and reads the copy again; at batch 1,
where a frame is the time to read the weights, that is half the frame. An unrolled copy (a
:class:`~motionflows.bijectors.Chain` of K separate steps, each weight its own buffer) skips
the copies and computes the same products in the same order: the same numbers up to
float32 rounding where XLA fuses the unrolled steps' small ops differently (bit for bit for
the shipped ``cpu`` MoGlow's samples, 1 and 256 sequences of 200 frames).

Measured on the 2-core AMD EPYC (docs/readme/speed.md, "Sampling from separate step
weights"): paper-size MoGlow ``sample`` at batch 1 26.6 -> 12.9 ms per frame, the shipped
``cpu`` MoGlow 0.53 -> 0.26 ms per frame (its samples bit-identical).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import jax
import jax.numpy as jnp
from flax import nnx

from motionflows.bijectors.base import Scan
from motionflows.nets.precision import MATMUL_WEIGHTS

__all__ = ["inference_copy", "stream_stepper", "streaming_model"]


def inference_copy(module: nnx.Module, compute_dtype: str | None = None) -> nnx.Module:
    """A copy of ``module`` for sampling and streaming, not for training.

    * Every :class:`~motionflows.bijectors.Scan` (stacked flow steps) becomes its
      :meth:`~motionflows.bijectors.Scan.unrolled` chain of K separate steps, so that a
      compiled frame reads each step's weights where they are stored instead of copying
      a slice of the stack first (see the module docstring). Same numbers (to float32
      rounding); the compiled frame grows with K (compile time: 3.4 against 4.0 s for the paper-size
      sampler, so no cost there). A stream state (``init_stream``) belongs to the model that
      made it: the copy's carries are a tuple per step, not a stacked array.
    * Every submodule with a ``compute_dtype`` attribute (the LSTM, MLP and convolution
      conditioners) *stores* its :data:`~motionflows.nets.precision.MATMUL_WEIGHTS` in the
      dtype it computes in, cast once. ``compute_dtype=None`` keeps each one's own: a
      float32 model stays float32, and a model trained with bfloat16 matmuls gets bfloat16
      weights, the same values its products cast them to, so the same numbers without a
      cast per frame (a single ``stream_step`` would otherwise convert all its weights
      every call). ``compute_dtype="bfloat16"`` makes
      every conditioner compute (float32 accumulation) and store in it: half the bytes a
      batch-1 frame reads, close to the float32 model, not equal. Biases, cell states, the
      flow's ActNorm / 1x1 maps and the base density stay float32.

    ``module`` itself is unchanged. Used by the library wherever a MoGlow samples
    (``experiments.moglow.sample``, so :mod:`motionflows.pretrained`, the bench and the CLI)
    and, for float32 models, streams (:func:`streaming_model`, ``motionflows play``).
    Any module works: one without a ``Scan`` or conditioners comes back as a plain clone.
    """
    copy = nnx.clone(module)
    _unroll_scans(copy)
    _store_weights_in(copy, None if compute_dtype is None else jnp.dtype(compute_dtype).name)
    return copy


def streaming_model(model: nnx.Module) -> nnx.Module:
    """The module a real-time loop should call ``stream_step`` on, one frame per call.

    A float32 model's :func:`inference_copy` (paper-size MoGlow at batch 1: 15 against 24
    ms a frame). A model whose conditioners compute in a low precision comes back as it
    is: a lone frame's program cannot hoist the weights' conversion out of a frame loop,
    and XLA:CPU's batch-1 bfloat16 products read ~1.5 GB/s, so its copy streams slower
    (112 ms a frame with bfloat16 weights, 129 with float32 ones converted every call)
    than the stacked model, whose weight slices are converted as they are copied (18 ms).
    Unmeasured on GPUs, where bfloat16 products are native.
    """
    low = any(
        getattr(node, "compute_dtype", None) is not None
        for _, node in nnx.iter_graph(model)
        if isinstance(node, nnx.Module)
    )
    return model if low else inference_copy(model)


def stream_stepper(model: Any) -> Callable:
    """``step(state, control_t, key, temperature) -> (pose_t, state)``: ``model.stream_step``
    jitted once, for a loop that calls it frame after frame.

    The weights enter the program as arguments, not constants baked into it. A Flax module is
    split once, here, into its graph and a flat list of arrays, and the jitted function
    rebuilds the module from them (``nnx.merge``) while tracing only: passing the module
    itself would have every call walk its graph in Python to flatten it, about 15 us per
    array. That cost grows with the arrays, and the :func:`inference_copy` that streams
    fastest holds K times more of them: for a K = 16, 2 x 64 MoGlow copy (272 arrays) a
    call took 8.3-9.9 ms with the module as the argument against 3.6-5.4 ms from the flat
    list on the 2-core EPYC (three runs), the same poses. Any other pytree model is passed
    as it is. ``temperature`` is traced: changing it does not recompile. The model's own
    state is not updated (as under ``jax.jit`` with the module as an argument):
    ``stream_step`` is pure in its key.
    """
    weights, rebuild = model, lambda weights: weights  # any pytree model: passed as it is
    if isinstance(model, nnx.Module):
        graphdef, state = nnx.split(model)
        weights, treedef = jax.tree.flatten(state)

        def rebuild(weights):  # runs while tracing only
            return nnx.merge(graphdef, jax.tree.unflatten(treedef, weights))

    jitted = jax.jit(
        lambda weights, state, control_t, key, temperature: rebuild(weights).stream_step(
            state, control_t, key, temperature=temperature
        )
    )
    return lambda state, control_t, key, temperature=1.0: jitted(
        weights, state, control_t, key, temperature
    )


def _unroll_scans(node: nnx.Module) -> None:
    """Replace, in place, every Scan held by ``node`` or its submodules by its chain."""
    is_list = isinstance(node, nnx.List)
    children = list(enumerate(node)) if is_list else list(vars(node).items())
    for name, value in children:
        if isinstance(value, Scan):
            value = value.unrolled()
            if is_list:
                node[name] = value
            else:
                setattr(node, name, value)
        if isinstance(value, nnx.Module):
            _unroll_scans(value)


def _store_weights_in(copy: nnx.Module, override: str | None) -> None:
    """Cast, in place, each conditioner's matmul weights to the dtype it computes in
    (``override`` first sets that dtype on every conditioner)."""
    for _, node in nnx.iter_graph(copy):
        if not isinstance(node, nnx.Module) or not hasattr(node, "compute_dtype"):
            continue
        if override is not None:
            node.compute_dtype = override
        name = node.compute_dtype
        if name is None:
            continue
        for attr in MATMUL_WEIGHTS & set(vars(node)):
            value = getattr(node, attr)
            params = value if isinstance(value, nnx.List) else [value]
            for param in params:
                if isinstance(param, nnx.Param):
                    param.set_value(param[...].astype(name))
