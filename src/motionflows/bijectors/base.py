"""The bijector interface and its combinators: ``Bijector``, ``Chain``, ``Inverse``,
``MapContext``, ``Scan``.

Direction (as in distrax, TFP, flowjax and the paper's x = f(z)):

* ``forward``  maps latent -> data (sampling):
  ``forward_and_log_det(z, *, context=None) -> (x, log|det dx/dz|)``
* ``inverse``  maps data -> latent (normalising, likelihood):
  ``inverse_and_log_det(x, *, context=None) -> (z, log|det dz/dx|)``

Events are sequences of shape (..., T, D) with any leading batch shape; every ``log_det`` has
the batch shape (...). ``context`` is an array (..., T, C) aligned in time with the event, or
None; every layer of a ``Chain`` / ``Scan`` receives the same context.

Frame by frame, with an explicit carry (autoregressive sampling, streaming, causal scoring):

* ``initial_carry(batch_shape=()) -> carry``  the state before frame 0 (a pytree),
* ``forward_step(z_t, *, context_t=None, carry) -> (x_t, log|det dx_t/dz_t|, carry)``,
* ``inverse_step(x_t, *, context_t=None, carry) -> (z_t, log|det dz_t/dx_t|, carry)``,

with frames x_t (..., D), context_t (..., C) and log-dets of the batch shape (...). Running a
step over t = 0 .. T-1 from ``initial_carry`` equals the sequence map (values and log-dets)
for every causal bijector. Stateless, per-frame bijectors inherit steps that run the sequence
map on one frame and pass the carry through; ``Chain`` and ``Scan`` thread one carry per layer
(``Chain``: a tuple in list order; ``Scan``: the steps' carries stacked on a leading K axis).

Per frame, for bijectors that map each frame by itself or from earlier frames (every
MoGlow layer; not ``Squeeze``, which mixes frames):
``inverse_and_frame_log_det(x, *, context=None) -> (z, log|det| per frame (..., T))``, whose
sum over T is ``inverse_and_log_det``'s log-det: what a loss that scores only some frames of
a window (a padded take's real frames) needs.

Data-dependent initialisation runs in an explicit "init mode" (see
:func:`motionflows.bijectors.initialize_from_data`): while it is active, bijectors are run
eagerly and layers with data-dependent parameters (``ActNorm``) set them from their input.
:func:`is_initializing` tells a model whether it is being run in that mode.
"""

from __future__ import annotations

import contextlib
import contextvars
from collections.abc import Callable, Iterator, Sequence
from typing import Any

import jax
import jax.numpy as jnp
from flax import nnx

from motionflows.deprecation import renamed

Array = jax.Array

__all__ = [
    "Bijector",
    "Chain",
    "Fixed",
    "Inverse",
    "MapContext",
    "Scan",
    "check_event",
    "check_frame",
    "data_init_mode",
    "is_initializing",
]


class Fixed(nnx.Variable):
    """A non-trainable array held by a bijector (a permutation matrix, a sign vector).

    It is an ``nnx.Variable`` but not an ``nnx.Param``, so optimisers and gradients taken
    over ``nnx.Param`` (``nnx.Optimizer(model, tx, wrt=nnx.Param)``,
    ``nnx.split(model, nnx.Param, ...)``) leave it alone; it is still part of the module's
    state, so checkpoints and ``nnx.vmap`` stacking carry it. Layers read it through
    ``jax.lax.stop_gradient`` so that even a gradient over the whole pytree is zero for it.
    """


# ----------------------------------------------------------------------------- init mode

_INIT_MODE: contextvars.ContextVar[bool] = contextvars.ContextVar(
    "motionflows_data_init_mode", default=False
)


def is_initializing() -> bool:
    """True while :func:`initialize_from_data` runs the model (eagerly) in init mode.

    Model code that loops with ``jax.lax.scan``/``jax.jit`` over layers containing
    ``ActNorm`` can check this and fall back to an eager Python loop during initialisation
    (``Scan`` does exactly that).
    """
    return _INIT_MODE.get()


@contextlib.contextmanager
def data_init_mode() -> Iterator[None]:
    """Context manager that switches init mode on (used by ``initialize_from_data``).

    Inside it, ``ActNorm.inverse_and_log_det`` overwrites its parameters from its input
    (mutating the module it is called on). Prefer :func:`initialize_from_data`, which works
    on a copy and so is pure.
    """
    token = _INIT_MODE.set(True)
    try:
        yield
    finally:
        _INIT_MODE.reset(token)


# ----------------------------------------------------------------------------- validation


def _at_least_float32(x: Any) -> Any:
    """``x`` in float32 when it is a lower-precision float (bfloat16, float16): a scanned
    flow's carry keeps one dtype, and its first ActNorm computes in float32 (as in a
    :class:`Chain`); float32 and float64 pass unchanged."""
    dtype = getattr(x, "dtype", None)
    if dtype is not None and jnp.issubdtype(dtype, jnp.floating) and dtype.itemsize < 4:
        return x.astype(jnp.float32)
    return x


def check_event(x: Any, num_channels: int | None, name: str, *, what: str = "inputs") -> None:
    """Raise a clear ``ValueError`` unless ``x`` is an array of shape (..., T, num_channels).

    Pure Python on static shapes: costs nothing under ``jax.jit``.
    """
    shape = getattr(x, "shape", None)
    if shape is None:
        raise ValueError(f"{name} expects an array of shape (..., T, D), got {type(x).__name__}")
    if len(shape) < 2:
        d = "D" if num_channels is None else num_channels
        raise ValueError(
            f"{name} expects (..., T, {d}) {what} (a time axis and a channel axis), "
            f"got shape {tuple(shape)}; add a time axis, e.g. x[..., None, :] for one frame"
        )
    dtype = getattr(x, "dtype", None)
    if dtype is not None and not jnp.issubdtype(dtype, jnp.floating):
        raise ValueError(
            f"{name} expects floating-point {what} (float32), got dtype {dtype}; "
            f"convert with x.astype(jnp.float32)"
        )
    if num_channels is not None and shape[-1] != num_channels:
        raise ValueError(
            f"{name} expects (..., T, {num_channels}) {what}, got shape {tuple(shape)} "
            f"({shape[-1]} channels instead of {num_channels})"
        )


def check_frame(x_t: Any, name: str, *, what: str = "frame") -> None:
    """Raise a clear ``ValueError`` unless ``x_t`` is one floating frame (..., D)."""
    shape = getattr(x_t, "shape", None)
    if shape is None or len(shape) < 1:
        raise ValueError(
            f"{name} expects one {what} of shape (..., D) (no time axis), got "
            f"{type(x_t).__name__ if shape is None else tuple(shape)}"
        )
    if not jnp.issubdtype(x_t.dtype, jnp.floating):
        raise ValueError(f"{name} expects a floating-point {what} (float32), got {x_t.dtype}")


def _one_frame(a: Array | None) -> Array | None:
    """(..., C) -> (..., 1, C): a frame as a one-frame sequence (None stays None)."""
    return None if a is None else a[..., None, :]


def _check_context(context: Any, x: Array, name: str) -> None:
    """A context, when given, is (..., T, C) with the event's T and a broadcastable batch."""
    if context is None:
        return
    shape = getattr(context, "shape", None)
    if shape is None or len(shape) < 2:
        raise ValueError(
            f"{name} expects context of shape (..., T, C) aligned in time with the event "
            f"(..., T, D) = {tuple(x.shape)}, got {shape if shape is not None else type(context)}"
        )
    if shape[-2] != x.shape[-2]:
        raise ValueError(
            f"{name}: context has {shape[-2]} time steps but the event has {x.shape[-2]}; "
            f"context must be (..., T, C) aligned with the event (..., T, D)"
        )
    try:
        batch = jnp.broadcast_shapes(tuple(shape[:-2]), tuple(x.shape[:-2]))
    except ValueError:
        batch = None
    if batch != tuple(x.shape[:-2]):
        raise ValueError(
            f"{name}: context batch shape {tuple(shape[:-2])} does not broadcast to the event "
            f"batch shape {tuple(x.shape[:-2])}"
        )


# ----------------------------------------------------------------------------- base class


class Bijector(nnx.Module):
    """An invertible map of sequences (..., T, D) -> (..., T', D') with exact log-dets.

    Subclasses implement ``forward_and_log_det`` (latent -> data) and
    ``inverse_and_log_det`` (data -> latent); ``forward`` and ``inverse`` are derived.
    Every bijector is a Flax NNX module, hence a pytree: pass it straight to ``jax.jit``,
    ``jax.grad``, ``jax.vmap`` or ``jax.lax.scan``.

    Examples:
      >>> import jax, jax.numpy as jnp
      >>> from motionflows import bijectors as bj
      >>> flow = bj.Chain([bj.InvertibleLinear(3, key=jax.random.key(0)), bj.Difference(3)])
      >>> z = jax.random.normal(jax.random.key(1), (2, 5, 3))     # (B, T, D) latents
      >>> x, log_det = flow.forward_and_log_det(z)               # the whole sequence
      >>> carry, frames = flow.initial_carry((2,)), []
      >>> for t in range(5):                                    # the same, frame by frame
      ...     x_t, ld_t, carry = flow.forward_step(z[:, t], carry=carry)
      ...     frames.append(x_t)
      >>> bool(jnp.allclose(jnp.stack(frames, 1), x, atol=1e-5))
      True
    """

    def forward_and_log_det(self, x: Array, *, context: Array | None = None) -> tuple[Array, Array]:
        """Latent -> data: returns (y, log|det dy/dx|) with log_det of the batch shape."""
        raise NotImplementedError

    def inverse_and_log_det(self, y: Array, *, context: Array | None = None) -> tuple[Array, Array]:
        """Data -> latent: returns (x, log|det dx/dy|) with log_det of the batch shape."""
        raise NotImplementedError

    frame_constant_log_det: bool = False
    """True where every frame contributes the same log-det (ActNorm, the 1x1 maps, permutations,
    ``Difference``, additive couplings): the default :meth:`inverse_and_frame_log_det` then
    spreads the sequence log-det evenly over the frames."""

    def inverse_and_frame_log_det(
        self, y: Array, *, context: Array | None = None
    ) -> tuple[Array, Array]:
        """Data -> latent with the log-det per frame: (x, log|det| (..., T)), whose sum over
        T is :meth:`inverse_and_log_det`'s. Defined for frame-wise bijectors only: those with
        ``frame_constant_log_det`` get log_det / T on every frame; couplings and the
        combinators override it; the rest raise."""
        if not self.frame_constant_log_det:
            raise NotImplementedError(
                f"{type(self).__name__} has no per-frame log-det (it is not a frame-wise "
                "map); score whole sequences with inverse_and_log_det"
            )
        x, ld = self.inverse_and_log_det(y, context=context)
        return x, jnp.broadcast_to((ld / y.shape[-2])[..., None], y.shape[:-1])

    def forward(self, x: Array, *, context: Array | None = None) -> Array:
        """Latent -> data."""
        return self.forward_and_log_det(x, context=context)[0]

    def inverse(self, y: Array, *, context: Array | None = None) -> Array:
        """Data -> latent."""
        return self.inverse_and_log_det(y, context=context)[0]

    # -- one frame at a time (explicit carry)

    def initial_carry(self, batch_shape: tuple[int, ...] = ()) -> Any:
        """The carry before frame 0 for frames of batch shape ``batch_shape``: () here."""
        del batch_shape
        return ()

    def forward_step(
        self, x_t: Array, *, context_t: Array | None = None, carry: Any = None
    ) -> tuple[Array, Array, Any]:
        """Latent -> data for one frame: x_t (..., D) -> (y_t, log|det dy_t/dx_t| (...), carry).

        ``carry=None`` starts from ``initial_carry(x_t.shape[:-1])``. This default is for
        stateless per-frame maps: the sequence map on the one-frame sequence
        x_t[..., None, :], the carry passed through. Bijectors that keep state override it.
        """
        check_frame(x_t, type(self).__name__)
        y, ld = self.forward_and_log_det(_one_frame(x_t), context=_one_frame(context_t))
        return y[..., 0, :], ld, self.initial_carry(x_t.shape[:-1]) if carry is None else carry

    def inverse_step(
        self, y_t: Array, *, context_t: Array | None = None, carry: Any = None
    ) -> tuple[Array, Array, Any]:
        """Data -> latent for one frame: y_t (..., D) -> (x_t, log|det dx_t/dy_t| (...), carry)."""
        check_frame(y_t, type(self).__name__)
        x, ld = self.inverse_and_log_det(_one_frame(y_t), context=_one_frame(context_t))
        return x[..., 0, :], ld, self.initial_carry(y_t.shape[:-1]) if carry is None else carry


def _zeros_batch(x: Array) -> Array:
    return jnp.zeros(x.shape[:-2], dtype=jnp.result_type(x.dtype, jnp.float32))


class Chain(Bijector):
    """Composition of bijectors. ``Chain([b1, b2, ..., bn])``:

    * ``forward`` (latent -> data) applies b1 first, then b2, ..., then bn:
      x = bn(...b2(b1(z))),
    * ``inverse`` (data -> latent) applies bn^-1 first, ..., b1^-1 last,

    and the log-dets add up. So a Glow step that, data -> latent, runs ActNorm, then the
    1x1 linear map, then the coupling is ``Chain([coupling, linear, actnorm])``;
    :meth:`from_data_to_latent` builds it from the data -> latent order instead.
    """

    def __init__(self, bijectors: Sequence[Bijector]):
        bijectors = list(bijectors)
        if not bijectors:
            raise ValueError("Chain needs at least one bijector")
        for b in bijectors:
            if not hasattr(b, "forward_and_log_det") or not hasattr(b, "inverse_and_log_det"):
                raise ValueError(
                    f"Chain items must be bijectors (with forward_and_log_det and "
                    f"inverse_and_log_det), got {type(b).__name__}"
                )
        self.bijectors = nnx.List(bijectors)

    @classmethod
    def from_data_to_latent(cls, bijectors: Sequence[Bijector]) -> Chain:
        """The chain whose inverse (data -> latent) applies ``bijectors`` in list order."""
        return cls(list(bijectors)[::-1])

    def __len__(self) -> int:
        return len(self.bijectors)

    def __getitem__(self, i: int) -> Bijector:
        return self.bijectors[i]

    def forward_and_log_det(self, x, *, context=None):
        total = None
        for b in self.bijectors:
            x, ld = b.forward_and_log_det(x, context=context)
            total = ld if total is None else total + ld
        return x, total

    def inverse_and_log_det(self, y, *, context=None):
        total = None
        for b in reversed(self.bijectors):
            y, ld = b.inverse_and_log_det(y, context=context)
            total = ld if total is None else total + ld
        return y, total

    def inverse_and_frame_log_det(self, y, *, context=None):
        total = None
        for b in reversed(self.bijectors):
            y, ld = b.inverse_and_frame_log_det(y, context=context)
            total = ld if total is None else total + ld
        return y, total

    def initial_carry(self, batch_shape=()):
        """One carry per bijector, a tuple in list order."""
        return tuple(b.initial_carry(batch_shape) for b in self.bijectors)

    def forward_step(self, x_t, *, context_t=None, carry=None):
        if carry is None:
            carry = self.initial_carry(x_t.shape[:-1])
        total, new = None, list(carry)
        for i, b in enumerate(self.bijectors):
            x_t, ld, new[i] = b.forward_step(x_t, context_t=context_t, carry=carry[i])
            total = ld if total is None else total + ld
        return x_t, total, tuple(new)

    def inverse_step(self, y_t, *, context_t=None, carry=None):
        if carry is None:
            carry = self.initial_carry(y_t.shape[:-1])
        total, new = None, list(carry)
        for i in reversed(range(len(self.bijectors))):
            y_t, ld, new[i] = self.bijectors[i].inverse_step(
                y_t, context_t=context_t, carry=carry[i]
            )
            total = ld if total is None else total + ld
        return y_t, total, tuple(new)


class Inverse(Bijector):
    """The inverse of a bijector: ``Inverse(b).forward == b.inverse`` and vice versa
    (the frame steps too; the carry is ``b``'s)."""

    def __init__(self, bijector: Bijector):
        self.bijector = bijector

    def forward_and_log_det(self, x, *, context=None):
        return self.bijector.inverse_and_log_det(x, context=context)

    def inverse_and_log_det(self, y, *, context=None):
        return self.bijector.forward_and_log_det(y, context=context)

    def initial_carry(self, batch_shape=()):
        return self.bijector.initial_carry(batch_shape)

    def forward_step(self, x_t, *, context_t=None, carry=None):
        return self.bijector.inverse_step(x_t, context_t=context_t, carry=carry)

    def inverse_step(self, y_t, *, context_t=None, carry=None):
        return self.bijector.forward_step(y_t, context_t=context_t, carry=carry)


class MapContext(Bijector):
    """A bijector that reads ``net(context)`` instead of ``context``: every map and frame
    step of ``MapContext(b, net)`` is ``b``'s with the context (..., T, C) or frame
    context_t (..., C) first mapped by ``net`` (a per-frame module, (..., C) -> (..., E)).

    The event and log-dets are ``b``'s (the context is not part of the event); so is the
    carry. A network shared by several bijectors' contexts runs once, not once per layer:
    ``MapContext(Scan(...), net)`` gives all K steps of a flow the same features net(c).
    """

    def __init__(self, bijector: Bijector, net: Callable[[Array], Array]):
        self.bijector = bijector
        self.net = net

    def _mapped(self, context):
        return None if context is None else self.net(context)

    def forward_and_log_det(self, x, *, context=None):
        return self.bijector.forward_and_log_det(x, context=self._mapped(context))

    def inverse_and_log_det(self, y, *, context=None):
        return self.bijector.inverse_and_log_det(y, context=self._mapped(context))

    def inverse_and_frame_log_det(self, y, *, context=None):
        return self.bijector.inverse_and_frame_log_det(y, context=self._mapped(context))

    def initial_carry(self, batch_shape=()):
        return self.bijector.initial_carry(batch_shape)

    def forward_step(self, x_t, *, context_t=None, carry=None):
        return self.bijector.forward_step(x_t, context_t=self._mapped(context_t), carry=carry)

    def inverse_step(self, y_t, *, context_t=None, carry=None):
        return self.bijector.inverse_step(y_t, context_t=self._mapped(context_t), carry=carry)


def _as_key(rngs: Any, key: Any = None) -> Array:
    if key is not None:
        return key
    if isinstance(rngs, nnx.Rngs):
        return rngs.params()
    if rngs is None:
        raise ValueError("Scan(factory, K, rngs=...) needs rngs (nnx.Rngs or a jax key)")
    return rngs


# Module-level scan bodies (the context rides along unchanged in the carry): a stable
# function identity lets JAX reuse the traced scan across eager calls.
def _forward_body(carry, step):
    h, total, context = carry
    h, ld = step.forward_and_log_det(h, context=context)
    return (h, total + ld, context), None


def _inverse_body(carry, step):
    h, total, context = carry
    h, ld = step.inverse_and_log_det(h, context=context)
    return (h, total + ld, context), None


def _inverse_frame_body(carry, step):
    h, total, context = carry
    h, ld = step.inverse_and_frame_log_det(h, context=context)
    return (h, total + ld, context), None


def _forward_step_body(acc, xs):
    h, total, context_t = acc
    step, carry = xs
    h, ld, carry = step.forward_step(h, context_t=context_t, carry=carry)
    return (h, total + ld, context_t), carry


def _inverse_step_body(acc, xs):
    h, total, context_t = acc
    step, carry = xs
    h, ld, carry = step.inverse_step(h, context_t=context_t, carry=carry)
    return (h, total + ld, context_t), carry


def _stack(steps: list[nnx.Module]) -> nnx.Module:
    """Stack equally structured modules into one whose arrays have a leading step axis."""
    try:
        return jax.tree.map(lambda *a: jnp.stack(a), *steps)
    except ValueError as e:
        raise ValueError(
            "Scan needs steps with identical structure (same classes, sizes and static "
            f"attributes such as permutations): {e}"
        ) from e


class Scan(Bijector):
    """K identical steps with stacked parameters, run by ``jax.lax.scan``.

    Numerically equal to ``Chain([step_0, ..., step_{K-1}])`` (see :meth:`unrolled`):
    ``forward`` (latent -> data) runs step 0 first and step K-1 last; ``inverse``
    (data -> latent) runs them in the reverse order. Compile time does not grow with K.
    Every step receives the same ``context``.

    Ways to build it:

    * ``Scan(factory, K, rngs=rngs)``: ``factory(rngs: nnx.Rngs) -> Bijector``
      builds one step; it is called once per key of ``jax.random.split(key, K)`` (as
      ``factory(nnx.Rngs(k))``) and the K results are stacked: the same random draws as
      ``nnx.vmap`` over those keys, at a fraction of the eager compile cost. The steps
      must share their structure (classes, sizes, static attributes) and differ only in
      array values; the factory must not keep ``rngs`` inside the step (no dropout).
    * ``Scan(stacked)`` or ``Scan(stacked, K)``: an existing module whose every array has a
      leading axis of size K (e.g. built with ``nnx.vmap``).
    * ``Scan([step_0, ..., step_{K-1}])``: stacks equally structured step modules.

    ``K`` is the number of steps, the name the models use for flow steps; ``num_steps=`` is
    its deprecated old keyword (and ``num_steps`` a read-only alias of the attribute ``K``).

    Attribute ``steps`` holds the stacked step module. Frame steps (``forward_step`` /
    ``inverse_step``) scan over the K steps the same way; the carry is the K steps' carries
    stacked on a leading K axis (``initial_carry``).

    During :func:`initialize_from_data` (init mode) the steps are run eagerly one by one
    (data -> latent order) and their updated parameters are written back into the stack.
    """

    def __init__(
        self,
        steps: Callable[[nnx.Rngs], Bijector] | nnx.Module | Sequence[nnx.Module],
        K: int | None = None,
        *,
        rngs: nnx.Rngs | Array | None = None,
        key: Array | None = None,
        num_steps: int | None = None,
    ):
        K = renamed(
            "Scan", old="num_steps", new="K", old_value=num_steps, new_value=K, default=None
        )
        if isinstance(steps, (list, tuple)):
            if not steps:
                raise ValueError("Scan needs at least one step")
            if K is not None and K != len(steps):
                raise ValueError(f"Scan got {len(steps)} steps but K={K}")
            K = len(steps)
            stacked = _stack(list(steps))
        elif isinstance(steps, nnx.Module):
            stacked = steps
            leaves = jax.tree.leaves(stacked)
            if not leaves:
                raise ValueError("Scan(stacked, K): the module holds no arrays")
            sizes = {leaf.shape[0] if leaf.ndim else None for leaf in leaves}
            if len(sizes) != 1 or None in sizes:
                raise ValueError(
                    "Scan(stacked, K): every array of the stacked module needs the "
                    f"same leading (step) axis; found leading sizes {sorted(map(str, sizes))}"
                )
            (size,) = sizes
            if K is None:
                K = size
            if size != K:
                raise ValueError(f"Scan(stacked, K={K}): the stacked arrays have {size} steps")
        elif callable(steps):
            if K is None or int(K) < 1:
                raise ValueError(f"Scan(factory, K) needs K >= 1, got {K}")
            keys = jax.random.split(_as_key(rngs, key), int(K))
            # Same values as nnx.vmap(lambda k: factory(nnx.Rngs(k)))(keys), but built one
            # step at a time and stacked: eagerly, the second and later steps reuse the
            # compiled primitives of the first, which makes construction several times
            # cheaper than vmapping the initialisers.
            stacked = _stack([steps(nnx.Rngs(k)) for k in keys])
        else:
            raise ValueError(
                "Scan(steps, K) expects a factory rngs -> Bijector, a stacked module "
                f"or a list of step modules, got {type(steps).__name__}"
            )
        self.steps = stacked
        self.K = int(K)

    @property
    def num_steps(self) -> int:
        """The old name of :attr:`K` (read-only)."""
        return self.K

    # -- access to single steps

    def step(self, k: int) -> Bijector:
        """A copy of step ``k`` (0 <= k < K) as an ordinary, unstacked module."""
        if not -self.K <= k < self.K:
            raise IndexError(f"Scan has {self.K} steps, asked for step {k}")
        return jax.tree.map(lambda a: a[k], self.steps)

    def unrolled(self) -> Chain:
        """The equivalent ``Chain([step_0, ..., step_{K-1}])`` (copies of the parameters)."""
        return Chain([self.step(k) for k in range(self.K)])

    # -- maps

    def forward_and_log_det(self, x, *, context=None):
        x = _at_least_float32(x)
        if is_initializing():
            return self._run_eagerly(x, context, forward=True)

        (x, total, _), _ = jax.lax.scan(_forward_body, (x, _zeros_batch(x), context), self.steps)
        return x, total

    def inverse_and_log_det(self, y, *, context=None):
        y = _at_least_float32(y)
        if is_initializing():
            return self._run_eagerly(y, context, forward=False)

        (y, total, _), _ = jax.lax.scan(
            _inverse_body, (y, _zeros_batch(y), context), self.steps, reverse=True
        )
        return y, total

    def inverse_and_frame_log_det(self, y, *, context=None):
        y = _at_least_float32(y)
        total = jnp.zeros(y.shape[:-1], jnp.result_type(y.dtype, jnp.float32))
        (y, total, _), _ = jax.lax.scan(
            _inverse_frame_body, (y, total, context), self.steps, reverse=True
        )
        return y, total

    def initial_carry(self, batch_shape=()):
        """The K steps' initial carries, stacked: every leaf gets a leading K axis."""
        return jax.vmap(lambda step: step.initial_carry(batch_shape))(self.steps)

    def forward_step(self, x_t, *, context_t=None, carry=None):
        x_t = _at_least_float32(x_t)
        if carry is None:
            carry = self.initial_carry(x_t.shape[:-1])
        acc = (x_t, jnp.zeros(x_t.shape[:-1], jnp.float32), context_t)
        (x_t, total, _), carry = jax.lax.scan(_forward_step_body, acc, (self.steps, carry))
        return x_t, total, carry

    def inverse_step(self, y_t, *, context_t=None, carry=None):
        y_t = _at_least_float32(y_t)
        if carry is None:
            carry = self.initial_carry(y_t.shape[:-1])
        acc = (y_t, jnp.zeros(y_t.shape[:-1], jnp.float32), context_t)
        (y_t, total, _), carry = jax.lax.scan(
            _inverse_step_body, acc, (self.steps, carry), reverse=True
        )
        return y_t, total, carry

    def _run_eagerly(self, h, context, *, forward: bool):
        """Init mode: run the steps one by one in Python and write them back (stacked)."""
        steps = [self.step(k) for k in range(self.K)]
        total = None
        for step in steps if forward else reversed(steps):
            run = step.forward_and_log_det if forward else step.inverse_and_log_det
            h, ld = run(h, context=context)
            total = ld if total is None else total + ld
        nnx.update(self.steps, nnx.state(_stack(steps)))
        return h, total
