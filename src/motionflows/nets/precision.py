"""Matrix products in float32 or in a low precision (bfloat16) with float32 accumulation.

:func:`matmul` is the one product the conditioner networks use (LSTM, MLP heads, the Glow
time convolution). With ``compute_dtype`` its backward pass is hand-written (a custom VJP)
so that the gradient products also run with low-precision operands and float32
accumulation; plain autodiff would upcast them to float32 (mixed-dtype dots). That mode is
reverse-mode only (``jax.grad``); float32 (``compute_dtype=None``) is plain JAX and supports
forward mode (``jax.jvp``, ``jax.jacfwd``) too.
"""

from __future__ import annotations

import functools
import warnings

import jax
import jax.numpy as jnp
from flax import nnx

Array = jax.Array

__all__ = ["MATMUL_WEIGHTS", "compute_dtype_name", "matmul", "outer_sum", "product"]

# The parameters the conditioner modules only ever use through :func:`matmul` (LSTM, MLP
# and convolution weights); biases, ActNorm and the 1x1 maps are never among them.
MATMUL_WEIGHTS = frozenset({"w_ih", "w_hh", "w_out", "ws", "kernel", "w_embed"})


def compute_dtype_name(dtype, where: str) -> str | None:
    """A model's ``compute_dtype`` argument as it is stored: None for float32 (None or
    "float32": plain float32 products, forward-mode differentiable), else "bfloat16" or
    "float16"; ValueError naming ``where`` for anything else."""
    if dtype is None:
        return None
    name = jnp.dtype(dtype).name
    if name == "float32":
        return None
    if name not in ("bfloat16", "float16"):
        raise ValueError(
            f"{where}: compute_dtype must be None/'float32', 'bfloat16' or 'float16', got {dtype!r}"
        )
    return name


def product(x: Array, w: Array, cd) -> Array:
    """x @ w with operands in ``cd`` (None: as given) and a float32 result."""
    if cd is None:
        return jnp.matmul(x, w)
    return jnp.matmul(x.astype(cd), w.astype(cd), preferred_element_type=jnp.float32)


def outer_sum(x: Array, g: Array, cd) -> Array:
    """sum over all leading axes of x[..., i] g[..., o]: (in, out) float32, one matmul."""
    x2 = x.reshape(-1, x.shape[-1])
    g2 = g.reshape(-1, g.shape[-1])
    return product(x2.T, g2, cd)


def matmul(x: Array, w: Array, compute_dtype: str | None = None) -> Array:
    """``x @ w`` for x (..., in), w (in, out): float32, or operands in ``compute_dtype``
    with float32 accumulation, in the backward pass too (dx = g @ w^T, dw = x^T g)."""
    if compute_dtype is None:
        return jnp.matmul(x, w)
    return _matmul_low(x, w, jnp.dtype(compute_dtype).name)


@functools.partial(jax.custom_vjp, nondiff_argnums=(2,))
def _matmul_low(x: Array, w: Array, cd: str) -> Array:
    return product(x, w, cd)


def _matmul_low_fwd(x, w, cd):
    return product(x, w, cd), (x, w)


def _matmul_low_bwd(cd, res, g):
    x, w = res
    return product(g, w.T, cd).astype(x.dtype), outer_sum(x, g, cd).astype(w.dtype)


_matmul_low.defvjp(_matmul_low_fwd, _matmul_low_bwd)


def inference_copy(module: nnx.Module, compute_dtype: str = "bfloat16") -> nnx.Module:
    """Deprecated: moved to :func:`motionflows.inference.inference_copy`, whose
    ``compute_dtype`` defaults to None (float32 weights, the same numbers) and which also
    unrolls the stacked flow steps. This old entry keeps its bfloat16 default."""
    from motionflows.inference import inference_copy as moved

    warnings.warn(
        "motionflows.nets.precision.inference_copy moved to "
        "motionflows.inference.inference_copy (compute_dtype there defaults to None)",
        DeprecationWarning,
        stacklevel=2,
    )
    return moved(module, compute_dtype)
