"""Input checks shared by the models' public entry points (one message per problem).

Every model's ``log_prob`` / ``sample`` / ``stream_step`` / ``elbo`` (and the experiment
wrappers) pass their array inputs through :func:`check_input` and the temperature through
:func:`check_temperature`, so a problem reads the same whichever model meets it:

* dtype: floating point only. float16, bfloat16 and float64 are cast to float32 (the
  project's compute dtype); integer, bool and complex arrays are refused.
* emptiness: every axis must have at least one entry (B >= 1 windows, T >= 1 frames).
* finiteness: NaN or inf anywhere is refused, with the index of the first one.
* temperature: a finite number >= 0.

Shapes and dtypes are static, so those checks also run under ``jax.jit``. Value checks
(finiteness, the temperature's value) need concrete arrays: they run at the Python
boundary and are skipped for tracers, which is why the experiment wrappers and
``motionflows.training.draw_samples`` check before they jit.
"""

from __future__ import annotations

import math
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from motionflows.deprecation import renamed


def is_concrete(x: Any) -> bool:
    """Whether ``x`` holds values now (not a tracer inside ``jax.jit`` / ``grad`` / ``scan``)."""
    return not isinstance(x, jax.core.Tracer)


def check_input(x: Any, name: str, where: str) -> jax.Array:
    """``x`` as a float32 array after the dtype, emptiness and finiteness checks.

    Args:
      x: an array (numpy, JAX, or anything ``jnp.asarray`` takes).
      name: what the argument is called (``"pose"``, ``"control"``, ``"seed_history"``).
      where: the entry point, e.g. ``"MoGlow.log_prob"``; it starts every message.
    Raises:
      ValueError: naming the entry point, the argument and the fix.
    """
    if x is None:
        raise ValueError(f"{where}: {name} is None; pass an array")
    dtype = getattr(x, "dtype", None)
    if dtype is None:
        try:
            x = np.asarray(x)
        except (TypeError, ValueError):
            raise ValueError(
                f"{where}: {name} must be a floating-point array, got {type(x).__name__}"
            ) from None
        dtype = x.dtype
    if not jnp.issubdtype(dtype, jnp.floating):
        raise ValueError(
            f"{where}: {name} must be a floating-point array (float32), got dtype {dtype}; "
            "convert it with .astype(np.float32)"
        )
    shape = tuple(np.shape(x))
    if any(n == 0 for n in shape):
        raise ValueError(
            f"{where}: {name} is empty (shape {shape}); it needs at least one window and one frame"
        )
    x = jnp.asarray(x, jnp.float32)
    if is_concrete(x):
        finite = np.isfinite(np.asarray(x))
        if not finite.all():
            first = tuple(int(i[0]) for i in np.nonzero(~finite))
            raise ValueError(
                f"{where}: {name} contains non-finite values (NaN or inf), the first at index "
                f"{first}; clean the data (or check the standardiser) before calling"
            )
    return x


def check_temperature(temperature: Any, where: str) -> Any:
    """``temperature`` unchanged if it is a finite number >= 0 (tracers pass through)."""
    if not is_concrete(temperature):
        return temperature
    try:
        value = float(np.asarray(temperature))
    except (TypeError, ValueError):
        raise ValueError(
            f"{where}: temperature must be a finite number >= 0, got {temperature!r}"
        ) from None
    if not (math.isfinite(value) and value >= 0.0):
        raise ValueError(
            f"{where}: temperature must be a finite number >= 0 (1 = the model's own spread, "
            f"0 = its mode), got {value:g}"
        )
    return temperature


def nearest_lengths(frames: int, multiple: int) -> list[int]:
    """The lengths nearest ``frames`` that are positive multiples of ``multiple``: the one
    below and the one above, or the smallest alone when ``frames`` is below it.

    >>> nearest_lengths(14, 4), nearest_lengths(2, 4)
    ([12, 16], [4])
    """
    lower = max(multiple, int(frames) // multiple * multiple)
    return [lower] if lower > frames else [lower, lower + multiple]


def check_length(length: int, multiple: int, rule: str, hint: str = "") -> None:
    """Refuse (``ValueError``) a window length T that is not a positive multiple of
    ``multiple``, offering the nearest lengths that are. ``rule`` says why the model needs
    it (the message's start); ``hint`` follows the offered lengths."""
    if length < multiple or length % multiple:
        use = " or ".join(map(str, nearest_lengths(length, multiple)))
        raise ValueError(f"{rule}; got T = {length}: use {use} frames{hint}")


def check_sample_args(
    control: Any,
    temperature: Any,
    seed_history: Any,
    where: str,
    *,
    control_dim: int = 3,
    seed_pose: Any = None,
) -> tuple[jax.Array, Any]:
    """The checks every experiment's ``sample(model, key, control, *, temperature,
    seed_history)`` makes before it jits: control (B, T, control_dim) floating, non-empty
    and finite, the temperature finite and >= 0, ``seed_history`` (if given) floating and
    finite. ``seed_pose`` is the deprecated old name of ``seed_history`` (a
    ``DeprecationWarning``). Returns (control, seed_history) as float32."""
    seed_history = renamed(
        where,
        old="seed_pose",
        new="seed_history",
        old_value=seed_pose,
        new_value=seed_history,
        default=None,
        stacklevel=4,  # the caller of the experiment's sample
    )
    shape = tuple(np.shape(control)) if control is not None else None
    if shape is None or len(shape) != 3 or shape[-1] != control_dim:
        raise ValueError(f"{where}: control must be (B, T, {control_dim}), got {shape}")
    control = check_input(control, "control", where)
    check_temperature(temperature, where)
    if seed_history is not None:
        seed_history = check_input(seed_history, "seed_history", where)
    return control, seed_history
