"""Renamed arguments: the old name keeps working for a while, with a ``DeprecationWarning``.

One name per concept across the models: ``K`` for flow steps (``MoGlow``, ``Glow``; the
experiments' configs already call it ``K``) and ``seed_history`` for the poses a sampler
starts from (``MoGlow``, ``VAELSTM``, ``LinearGaussianAR`` and every experiment's
``sample``, whose old keyword was ``seed_pose``).

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

__all__ = ["renamed"]


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
