"""Renamed arguments: the old name keeps working for a while, with a ``DeprecationWarning``.

One name per concept across the models: ``K`` for flow steps (``MoGlow``, ``Glow``; the
experiments' configs already call it ``K``) and ``seed_history`` for the poses a sampler
starts from (``MoGlow``, ``VAELSTM``, ``LinearGaussianAR`` and every experiment's
``sample``, whose old keyword was ``seed_pose``), and one argument order for ``sample``: key
before control, ``model.sample(key, control)`` and an experiment's ``sample(model, key,
control)`` (whose old order was ``(model, control, key)``: :func:`key_first`).

Examples:
    >>> import warnings
    >>> with warnings.catch_warnings(record=True) as caught:
    ...     warnings.simplefilter("always")
    ...     renamed("f", old="steps", new="K", old_value=4, new_value=None, default=16)
    4
    >>> caught[0].category.__name__
    'DeprecationWarning'
    >>> renamed("f", old="steps", new="K", old_value=None, new_value=None, default=16)
    16
"""

from __future__ import annotations

import warnings
from typing import Any

import numpy as np

__all__ = ["is_key", "key_first", "renamed"]


def renamed(
    where: str,
    *,
    old: str,
    new: str,
    old_value: Any,
    new_value: Any,
    default: Any,
    stacklevel: int = 3,
):
    """The value of an argument renamed from ``old`` to ``new`` (both keyword, None = not
    given): ``new_value``, else ``old_value`` with a ``DeprecationWarning``, else
    ``default``. Both given is a ``TypeError`` naming the one to keep. ``stacklevel`` as
    in ``warnings.warn`` (3: the caller of the function that calls ``renamed``)."""
    if old_value is None:
        return default if new_value is None else new_value
    if new_value is not None:
        raise TypeError(f"{where}: pass {new}= only ({old}= is its old, deprecated name)")
    warnings.warn(
        f"{where}: {old}= is deprecated, use {new}= (same meaning)",
        DeprecationWarning,
        stacklevel=stacklevel,
    )
    return old_value


def is_key(x: Any) -> bool:
    """True for a JAX PRNG key: a typed key array (``jax.random.key``) or a raw uint32 key
    of shape (..., 2) (``jax.random.PRNGKey``); False for poses, controls and None."""
    import jax

    dtype = getattr(x, "dtype", None)
    if dtype is None:
        return False
    if jax.dtypes.issubdtype(dtype, jax.dtypes.prng_key):
        return True
    return dtype == np.uint32 and np.ndim(x) >= 1 and np.shape(x)[-1] == 2


def key_first(where: str, key: Any, control: Any, *, stacklevel: int = 3) -> tuple[Any, Any]:
    """``(key, control)`` of a ``sample(model, key, control)`` call, also when it was made in
    the old order ``sample(model, control, key)`` (then with a ``DeprecationWarning``): the
    two are told apart by type (a key array against a floating control), so jitted callers
    work too.

    Examples:
        >>> import jax, warnings
        >>> k, c = jax.random.key(0), jax.numpy.zeros((1, 4, 3))
        >>> key_first("f", k, c)[1].shape
        (1, 4, 3)
        >>> with warnings.catch_warnings(record=True) as caught:
        ...     warnings.simplefilter("always")
        ...     key_first("f", c, k)[1].shape
        (1, 4, 3)
        >>> caught[0].category.__name__
        'DeprecationWarning'
    """
    if is_key(control) and not is_key(key):
        warnings.warn(
            f"{where}: the argument order (model, control, key) is deprecated, use "
            "(model, key, control), the order of model.sample(key, control)",
            DeprecationWarning,
            stacklevel=stacklevel,
        )
        return control, key
    return key, control
