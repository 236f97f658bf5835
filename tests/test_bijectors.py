"""Generic, registry-driven checks of every bijector, plus the specific ones.

Every entry of ``REGISTRY`` builds a bijector with non-trivial random parameters (every
``nnx.Param`` is perturbed, so zero-initialised conditioner heads and ActNorm are not the
identity) and goes through the same checks: round trips both ways, log-dets against
``jax.jacfwd`` + ``slogdet`` of the flattened (T * D) event in both directions, forward
log-det = -inverse log-det, jit / vmap = eager, batch shapes (), (B,), (B1, B2), the context
changing the output when the conditioner uses it, and clear ``ValueError`` on bad shapes.
Every entry that runs frame by frame (``forward_step`` / ``inverse_step`` with an explicit
carry) must also match its sequence maps frame by frame, with exact per-frame log-dets.
"""

from __future__ import annotations

import dataclasses
import functools
from collections.abc import Callable

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from flax import nnx

from motionflows import bijectors as bj
from motionflows.nets import MLP, coupling_mlp

pytestmark = pytest.mark.usefixtures("fast_compilation")

T, D, C = 4, 5, 2  # odd D exercises the floor/ceil halves
K_STEPS = 3


# ----------------------------------------------------------------------------- helpers


def perturb(module, seed, scale=0.3):
    """Add N(0, scale^2) noise to every nnx.Param of ``module`` (in place) and return it.

    The noise comes from numpy (seeded), which costs no XLA compilation per leaf shape.
    """
    rng = np.random.default_rng(seed)
    state = nnx.state(module, nnx.Param)
    leaves, treedef = jax.tree.flatten(state)
    new = [
        jnp.asarray(np.asarray(leaf) + scale * rng.standard_normal(leaf.shape), leaf.dtype)
        for leaf in leaves
    ]
    nnx.update(module, jax.tree.unflatten(treedef, new))
    return module


class ShiftConv(nnx.Module):
    """A causal two-tap convolution over time: a *sequence* conditioner (sees x_{t-1}).

    ``step`` runs one frame; its carry is the previous frame x_{t-1} (zero before frame 0).
    """

    def __init__(self, fin, fout, context_features, *, rngs):
        self.w0 = nnx.Param(0.5 * jax.random.normal(rngs.params(), (fin, 8)))
        self.w1 = nnx.Param(0.5 * jax.random.normal(rngs.params(), (fin, 8)))
        self.v = nnx.Param(0.5 * jax.random.normal(rngs.params(), (context_features, 8)))
        self.out = nnx.Param(jnp.zeros((8, fout)))  # zero head, perturbed by the registry

    def __call__(self, x, context):
        prev = jnp.concatenate([jnp.zeros_like(x[..., :1, :]), x[..., :-1, :]], axis=-2)
        h = x @ self.w0[...] + prev @ self.w1[...]
        if context is not None:
            h = h + context @ self.v[...]
        return jnp.tanh(h) @ self.out[...]

    def initial_carry(self, batch_shape=()):
        return jnp.zeros((*batch_shape, self.w0.shape[0]))

    def step(self, x_t, context_t, carry):
        h = x_t @ self.w0[...] + carry @ self.w1[...]
        if context_t is not None:
            h = h + context_t @ self.v[...]
        return jnp.tanh(h) @ self.out[...], x_t


class ContextNet(nnx.Module):
    """A per-frame nonlinear map of the context, (..., C) -> (..., C), for ``MapContext``."""

    def __init__(self, c, *, rngs):
        self.w = nnx.Param(jax.random.normal(rngs.params(), (c, c)))

    def __call__(self, context):
        return jnp.tanh(context @ self.w[...])


def _glow_step(rngs, *, context_features=C):
    """data -> latent: ActNorm, InvertibleLinear, AffineCoupling (per-frame MLP)."""
    cond = coupling_mlp(D, context_features=context_features, hidden=8, rngs=rngs)
    return bj.Chain.from_data_to_latent(
        [bj.ActNorm(D), bj.InvertibleLinear(D, rngs=rngs), bj.AffineCoupling(D, cond)]
    )


def _sequence_step(rngs):
    """A MoGlow-like step: the coupling's conditioner carries state along time."""
    cond = ShiftConv(D // 2, 2 * (D - D // 2), C, rngs=rngs)
    return bj.Chain.from_data_to_latent(
        [bj.ActNorm(D), bj.InvertibleLinear(D, rngs=rngs), bj.AffineCoupling(D, cond)]
    )


@dataclasses.dataclass(frozen=True)
class Case:
    build: Callable[[nnx.Rngs], bj.Bijector]
    uses_context: bool = False
    steps: bool = True  # runs frame by frame (forward_step / inverse_step)
    bad_data: tuple = ((T, D + 1), (D,))  # shapes inverse() must reject
    bad_latent: tuple = ((T, D + 1), (D,))  # shapes forward() must reject


REGISTRY: dict[str, Case] = {
    "actnorm": Case(lambda r: bj.ActNorm(D)),
    "invertible_linear": Case(lambda r: bj.InvertibleLinear(D, rngs=r)),
    "dense_linear": Case(lambda r: bj.DenseLinear(D, rngs=r)),
    "permute": Case(lambda r: bj.Permute.random(D, key=r.params())),
    "reverse": Case(lambda r: bj.Reverse(D)),
    "affine_coupling_mlp": Case(lambda r: bj.AffineCoupling(D, coupling_mlp(D, hidden=8, rngs=r))),
    "affine_coupling_mlp_context": Case(
        lambda r: bj.AffineCoupling(D, coupling_mlp(D, context_features=C, hidden=8, rngs=r)),
        uses_context=True,
    ),
    "affine_coupling_sequence_context": Case(
        lambda r: bj.AffineCoupling(D, ShiftConv(D // 2, 2 * (D - D // 2), C, rngs=r)),
        uses_context=True,
    ),
    "additive_coupling_context": Case(
        lambda r: bj.AdditiveCoupling(
            D, coupling_mlp(D, context_features=C, hidden=8, additive=True, rngs=r)
        ),
        uses_context=True,
    ),
    "chain": Case(_glow_step, uses_context=True),
    "map_context_scan_sequence": Case(
        lambda r: bj.MapContext(bj.Scan(_sequence_step, K_STEPS, rngs=r), ContextNet(C, rngs=r)),
        uses_context=True,
    ),
    "inverse_of_chain": Case(lambda r: bj.Inverse(_glow_step(r)), uses_context=True),
    "scan": Case(lambda r: bj.Scan(_glow_step, K_STEPS, rngs=r), uses_context=True),
    "scan_sequence": Case(lambda r: bj.Scan(_sequence_step, K_STEPS, rngs=r), uses_context=True),
    "difference": Case(lambda r: bj.Difference(D)),
    "leaky_difference": Case(lambda r: bj.Difference(D, decay=0.8)),
    "squeeze": Case(
        lambda r: bj.Squeeze(2),
        steps=False,
        bad_data=((T + 1, D), (D,)),
        bad_latent=((T, 2 * D + 1), (D,)),
    ),
}

NAMES = sorted(REGISTRY)
CONTEXT_NAMES = [n for n in NAMES if REGISTRY[n].uses_context]
STEP_NAMES = [n for n in NAMES if REGISTRY[n].steps]
NO_FRAME_LOG_DET = {"inverse_of_chain"}  # its per-frame log-det would be the forward one's
VOLUME_PRESERVING = {
    "permute", "reverse", "squeeze", "additive_coupling_context", "difference", "leaky_difference"
}  # fmt: skip


@functools.cache
def built(name: str) -> bj.Bijector:
    """The registry entry, built once with perturbed (non-identity) parameters."""
    rngs = nnx.Rngs(NAMES.index(name))
    return perturb(REGISTRY[name].build(rngs), 7, scale=0.15)


def data(name, batch, seed=0):
    """(x, context) for the entry: x (*batch, T, D), context (*batch, T, C) or None."""
    kx, kc = jax.random.split(jax.random.key(seed))
    x = 1.5 * jax.random.normal(kx, (*batch, T, D)) + 0.3
    c = jax.random.normal(kc, (*batch, T, C)) if REGISTRY[name].uses_context else None
    return x, c


def latent_shape(name, batch):
    bij = built(name)
    x, c = data(name, batch)
    return jax.eval_shape(lambda: bij.inverse(x, context=c)).shape


@functools.cache
def report(name: str) -> dict:
    """Everything the generic checks look at, computed by ONE compiled function per entry
    (one XLA compilation instead of dozens keeps the suite fast on 2 CPU cores; eager
    execution is compared with it in test_jit_and_vmap_agree_with_eager)."""
    bij = built(name)
    x3, c3 = data(name, (3,))
    x23, c23 = data(name, (2, 3))
    x0, c0 = data(name, ())
    zshape0 = latent_shape(name, ())
    zr = jax.random.normal(jax.random.key(3), latent_shape(name, (3,)))
    zr0 = jax.random.normal(jax.random.key(5), zshape0)

    @jax.jit
    def run(b, x3, c3, x23, c23, x0, c0, zr, zr0):
        def inv(x, c):
            return b.inverse_and_log_det(x, context=c)

        def fwd(z, c):
            return b.forward_and_log_det(z, context=c)

        out = {"inv": inv(x3, c3)}
        out["fwd_of_inv"] = fwd(out["inv"][0], c3)
        out["fwd"] = fwd(zr, c3)
        out["inv_of_fwd"] = inv(out["fwd"][0], c3)
        out["vmap_inv"] = jax.vmap(inv)(x3, c3)
        out["vmap_fwd"] = jax.vmap(fwd)(out["inv"][0], c3)
        # log-dets and Jacobians of single (T, D) events
        out["inv0"] = inv(x0, c0)
        out["fwd0"] = fwd(zr0, c0)
        j_inv = jax.jacfwd(lambda v: inv(v.reshape(x0.shape), c0)[0].reshape(-1))
        j_fwd = jax.jacfwd(lambda v: fwd(v.reshape(zshape0), c0)[0].reshape(-1))
        out["slogdet_inv"] = jnp.linalg.slogdet(j_inv(x0.reshape(-1)))
        out["slogdet_fwd"] = jnp.linalg.slogdet(j_fwd(zr0.reshape(-1)))
        # batch shapes (B1, B2) and (B,), and single elements of the (B1, B2) batch
        out["inv23"] = inv(x23, c23)
        out["fwd23"] = fwd(out["inv23"][0], c23)
        c6 = None if c23 is None else c23.reshape(6, T, C)
        out["inv6"] = inv(x23.reshape(6, T, D), c6)
        out["fwd6"] = fwd(out["inv6"][0], c6)
        for i, j in [(0, 0), (1, 2)]:
            ci = None if c23 is None else c23[i, j]
            out[f"inv23_{i}{j}"] = inv(x23[i, j], ci)
            out[f"fwd23_{i}{j}"] = fwd(out[f"inv23_{i}{j}"][0], ci)
        if c3 is not None:
            out["inv_c2"] = inv(x3, c3 + 1.0)
            out["fwd_c2"] = fwd(out["inv"][0], c3 + 1.0)
        return out

    out = run(bij, x3, c3, x23, c23, x0, c0, zr, zr0)
    out.update(x3=x3, c3=c3, x23=x23, zr=zr)
    return out


def close(a, b, tol=2e-4):
    np.testing.assert_allclose(np.asarray(a), np.asarray(b), rtol=tol, atol=tol)


# ----------------------------------------------------------------------------- generic


@pytest.mark.parametrize("name", NAMES)
def test_round_trip_both_ways(name):
    r = report(name)
    z, _ = r["inv"]
    assert z.dtype == jnp.float32
    close(r["fwd_of_inv"][0], r["x3"])  # data -> latent -> data
    close(r["inv_of_fwd"][0], r["zr"])  # latent -> data -> latent
    # not the identity (the registry promises non-trivial parameters), except Squeeze,
    # whose latent holds the data's numbers in another shape
    if name != "squeeze":
        assert float(jnp.max(jnp.abs(z - r["x3"]))) > 1e-2


@pytest.mark.parametrize("name", NAMES)
def test_log_det_matches_jacobian_both_directions(name):
    r = report(name)
    for direction in ("inv", "fwd"):
        ld = r[f"{direction}0"][1]
        sign, ref = r[f"slogdet_{direction}"]
        assert ld.shape == ()
        assert float(sign) != 0.0
        close(ld, ref, tol=5e-4)


@pytest.mark.parametrize("name", NAMES)
def test_forward_log_det_is_minus_inverse_log_det(name):
    r = report(name)
    close(r["fwd_of_inv"][1], -r["inv"][1])  # at matching points x <-> z
    close(r["inv_of_fwd"][1], -r["fwd"][1])
    if name not in VOLUME_PRESERVING:
        assert float(jnp.max(jnp.abs(r["inv"][1]))) > 1e-3


@pytest.mark.parametrize("name", NAMES)
def test_jit_and_vmap_agree_with_eager(name):
    bij = built(name)
    r = report(name)
    x, c = r["x3"], r["c3"]
    z, ld = bij.inverse_and_log_det(x, context=c)  # eager
    x_back, ld_f = bij.forward_and_log_det(z, context=c)  # eager
    close(r["inv"][0], z)
    close(r["inv"][1], ld)
    close(r["fwd_of_inv"][0], x_back)
    close(r["fwd_of_inv"][1], ld_f)
    close(r["vmap_inv"][0], z)  # vmap over the batch of unbatched (T, D) calls
    close(r["vmap_inv"][1], ld)
    close(r["vmap_fwd"][0], x_back)
    close(r["vmap_fwd"][1], ld_f)


@pytest.mark.parametrize("name", NAMES)
def test_batch_shapes(name):
    r = report(name)
    z, ld = r["inv23"]
    assert ld.shape == (2, 3) and r["fwd23"][1].shape == (2, 3)
    assert z.shape[:2] == (2, 3)
    close(r["fwd23"][0], r["x23"])
    for i, j in [(0, 0), (1, 2)]:  # each element equals its own unbatched computation
        zi, ldi = r[f"inv23_{i}{j}"]
        assert ldi.shape == () and r[f"fwd23_{i}{j}"][1].shape == ()
        close(zi, z[i, j])
        close(ldi, ld[i, j])
        close(r[f"fwd23_{i}{j}"][0], r["x23"][i, j])
    z6, ld6 = r["inv6"]
    assert ld6.shape == (6,) and r["fwd6"][1].shape == (6,)
    close(z6.reshape(z.shape), z)
    close(ld6.reshape(2, 3), ld)
    close(r["fwd6"][0].reshape(r["x23"].shape), r["x23"])


@pytest.mark.parametrize("name", CONTEXT_NAMES)
def test_context_changes_output(name):
    r = report(name)
    assert float(jnp.max(jnp.abs(r["inv_c2"][0] - r["inv"][0]))) > 1e-3
    assert float(jnp.max(jnp.abs(r["fwd_c2"][0] - r["fwd_of_inv"][0]))) > 1e-3


def test_map_context_is_the_bijector_given_the_mapped_context():
    """Every map and frame step of MapContext(b, net) is b's on net(context)."""
    wrapped = built("map_context_scan_sequence")
    inner, net = wrapped.bijector, wrapped.net
    x, c = data("map_context_scan_sequence", (2,))
    for name in ("inverse_and_log_det", "forward_and_log_det"):
        got = getattr(wrapped, name)(x, context=c)
        close(got[0], getattr(inner, name)(x, context=net(c))[0], 1e-6)
        close(got[1], getattr(inner, name)(x, context=net(c))[1], 1e-6)
    carry = wrapped.initial_carry((2,))
    for name in ("inverse_step", "forward_step"):
        got = getattr(wrapped, name)(x[:, 0], context_t=c[:, 0], carry=carry)
        want = getattr(inner, name)(x[:, 0], context_t=net(c[:, 0]), carry=carry)
        for a, b in zip(jax.tree.leaves(got), jax.tree.leaves(want), strict=True):
            close(a, b, 1e-6)


@pytest.mark.parametrize("name", NAMES)
def test_wrong_shapes_raise_clear_value_error(name):
    bij = built(name)
    case = REGISTRY[name]
    c1 = jnp.zeros((T, C)) if case.uses_context else None
    for shape in case.bad_data:
        c = c1 if len(shape) == 2 and shape[0] == T else None
        with pytest.raises(ValueError, match=r"expects|needs"):
            bij.inverse_and_log_det(jnp.zeros(shape), context=c)
    for shape in case.bad_latent:
        c = c1 if len(shape) == 2 and shape[0] == T else None
        with pytest.raises(ValueError, match=r"expects|needs"):
            bij.forward_and_log_det(jnp.zeros(shape), context=c)


def test_integer_input_and_mismatched_steps_raise():
    with pytest.raises(ValueError, match="floating-point"):
        bj.ActNorm(D).inverse(jnp.zeros((T, D), jnp.int32))
    with pytest.raises(ValueError, match="identical structure"):
        bj.Scan([bj.ActNorm(D), bj.ActNorm(D + 1)])
    with pytest.raises(ValueError, match="identical structure"):
        bj.Scan([bj.Permute([0, 1, 2]), bj.Permute([2, 1, 0])])


@pytest.mark.parametrize("name", CONTEXT_NAMES)
def test_misaligned_context_raises(name):
    bij = built(name)
    x, _ = data(name, (3,))
    with pytest.raises(ValueError, match="context"):
        bij.inverse(x, context=jnp.zeros((3, T + 1, C)))


# ----------------------------------------------------------------------------- frame steps


@functools.cache
def step_report(name: str) -> dict:
    """Frame-by-frame runs of an entry (one compiled function, as :func:`report`)."""
    bij = built(name)
    x, c = data(name, (3,))
    z = jax.random.normal(jax.random.key(3), x.shape)

    @jax.jit
    def run(b, x, c, z):
        def frames(step, seq):
            carry, outs, lds = b.initial_carry((3,)), [], []
            for t in range(seq.shape[1]):
                c_t = None if c is None else c[:, t]
                y_t, ld_t, carry = step(seq[:, t], context_t=c_t, carry=carry)
                outs.append(y_t)
                lds.append(ld_t)
            return jnp.stack(outs, 1), jnp.stack(lds, 1), carry

        out = {
            "inv_seq": b.inverse_and_log_det(x, context=c),
            "fwd_seq": b.forward_and_log_det(z, context=c),
            "inv_steps": frames(b.inverse_step, x),
            "fwd_steps": frames(b.forward_step, z),
        }
        if name not in NO_FRAME_LOG_DET:
            out["inv_frame_ld"] = b.inverse_and_frame_log_det(x, context=c)
        # exact per-frame log-dets: the Jacobian of frame t's map with the carry held fixed
        # (the carry after frames 0 .. T-2), one batch element
        carry = frames(b.inverse_step, x[:, : T - 1])[2]
        c_t = None if c is None else c[:, T - 1]
        for direction, step, u in (("inv", b.inverse_step, x), ("fwd", b.forward_step, z)):

            def one(v, step=step, u=u):
                full = u[:, T - 1].at[0].set(v)
                y_t, ld_t, _ = step(full, context_t=c_t, carry=carry)
                return y_t[0], ld_t[0]

            out[f"jac_{direction}"] = jnp.linalg.slogdet(jax.jacfwd(lambda v: one(v)[0])(u[0, -1]))
            out[f"ld_{direction}"] = one(u[0, -1])[1]
        return out

    return run(bij, x, c, z)


@pytest.mark.parametrize("name", STEP_NAMES)
def test_frame_steps_equal_sequence_maps(name):
    r = step_report(name)
    for direction in ("inv", "fwd"):
        seq, ld_seq = r[f"{direction}_seq"]
        frames, ld_frames, _ = r[f"{direction}_steps"]
        assert ld_frames.shape == (3, T)
        close(frames, seq, 1e-5)
        close(jnp.sum(ld_frames, axis=1), ld_seq, 1e-4)


@pytest.mark.parametrize("name", [n for n in STEP_NAMES if n not in NO_FRAME_LOG_DET])
def test_frame_log_dets_are_the_frame_steps(name):
    """inverse_and_frame_log_det gives each frame's log-det of the one sequence pass: the
    frame steps' own (so the sum is the sequence log-det, and a loss may score some frames)."""
    r = step_report(name)
    z, ld = r["inv_frame_ld"]
    _, ld_steps, _ = r["inv_steps"]
    assert ld.shape == (3, T)
    close(z, r["inv_seq"][0], 1e-5)
    close(ld, ld_steps, 1e-4)
    if not built(name).frame_constant_log_det:  # affine couplings: the frames differ
        assert float(jnp.std(ld[0])) > 1e-3


def test_frame_log_dets_of_other_bijectors_raise():
    x, c = data("inverse_of_chain", (3,))
    for bij, context in ((built("inverse_of_chain"), c), (bj.Squeeze(2), None)):
        with pytest.raises(NotImplementedError, match="per-frame log-det"):
            bij.inverse_and_frame_log_det(x, context=context)


@pytest.mark.parametrize("name", STEP_NAMES)
def test_frame_step_log_det_matches_jacobian(name):
    r = step_report(name)
    for direction in ("inv", "fwd"):
        sign, ref = r[f"jac_{direction}"]
        assert float(sign) != 0.0
        close(r[f"ld_{direction}"], ref, tol=5e-4)


def test_frame_step_carries():
    """Stateless steps pass the carry through; Chain and Scan thread one carry per layer."""
    scan = built("scan_sequence")
    carry = scan.initial_carry((3,))
    coupling_state, (w, w_inv), actnorm_state = carry  # Chain order: coupling, 1x1, ActNorm
    assert actnorm_state == ()
    assert coupling_state.shape == (K_STEPS, 3, D // 2)  # ShiftConv: the previous x_a frame
    assert w.shape == w_inv.shape == (K_STEPS, D, D)
    close(jnp.einsum("kij,kjl->kil", w, w_inv), jnp.broadcast_to(jnp.eye(D), w.shape), 1e-5)
    x, c = data("scan_sequence", (3,))
    _, _, new = scan.inverse_step(x[:, 0], context_t=c[:, 0], carry=carry)
    close(new[1][0], w, 0)  # the 1x1 maps are carried unchanged ...
    assert not np.allclose(new[0], coupling_state)  # ... the conditioner state moves on
    # carry=None starts from initial_carry
    close(scan.inverse_step(x[:, 0], context_t=c[:, 0])[0], scan.inverse_step(
        x[:, 0], context_t=c[:, 0], carry=carry)[0], 0)  # fmt: skip
    # a Difference started from a known frame adds it back
    diff = bj.Difference(D)
    y_t, ld_t, prev = diff.forward_step(x[:, 1], carry=x[:, 0])
    close(y_t, x[:, 0] + x[:, 1], 0)
    close(prev, y_t, 0)
    assert ld_t.shape == (3,)


def test_frames_of_frame_mixing_bijectors_raise():
    with pytest.raises(ValueError, match="per-frame step"):
        bj.Squeeze(2).inverse_step(jnp.zeros((3, D)))
    with pytest.raises(ValueError, match="frames"):
        built("invertible_linear").forward_step(jnp.zeros((3, D + 1)))
    with pytest.raises(ValueError, match="one frame"):
        bj.ActNorm(D).inverse_step(jnp.float32(1.0))


def test_leaky_difference_forgets_an_error_geometrically():
    """decay a: u_t = x_t - a x_{t-1}, so one changed u_k moves x_t by a^(t-k) (t >= k),
    where the plain difference moves every later frame by the whole change."""
    x = jax.random.normal(jax.random.key(3), (6, 2))
    bump = jnp.zeros((6, 2)).at[1].set(1.0)
    for decay, expected in ((0.5, 0.5 ** np.arange(5)), (1.0, np.ones(5))):
        diff = bj.Difference(2, decay=decay)
        u = diff.inverse_and_log_det(x)[0]
        close(u[1:], x[1:] - decay * x[:-1], 1e-6)
        moved = diff.forward_and_log_det(u + bump)[0] - x
        close(moved[1:, 0], expected, 1e-5)
        close(moved[0], jnp.zeros(2), 1e-6)
    with pytest.raises(ValueError, match="0 < decay <= 1"):
        bj.Difference(2, decay=0.0)


def test_difference_with_move_names_the_missing_context_on_every_path():
    diff = bj.Difference(D, move=lambda previous, c: previous + jnp.sum(c))
    x = jnp.ones((2, 4, D))
    for call in (
        lambda: diff.forward_and_log_det(x),
        lambda: diff.inverse_and_log_det(x),
        lambda: diff.forward_step(x[:, 0]),
        lambda: diff.inverse_step(x[:, 0]),
    ):
        with pytest.raises(ValueError, match="needs the context of each frame"):
            call()


# ----------------------------------------------------------------------------- ActNorm init


def _channel_stats(z):
    flat = np.asarray(z).reshape(-1, z.shape[-1])
    return flat.mean(0), flat.std(0)


def test_actnorm_formula():
    an = bj.ActNorm(D)
    an.bias[...] = jnp.arange(D, dtype=jnp.float32)
    an.logs[...] = jnp.linspace(-0.5, 0.5, D)
    x = jax.random.normal(jax.random.key(0), (2, T, D))
    z, ld = an.inverse_and_log_det(x)
    close(z, (x + an.bias[...]) * jnp.exp(an.logs[...]))
    close(ld, jnp.full((2,), T * jnp.sum(an.logs[...])))


def test_initialize_from_data_normalises_and_is_pure():
    an = bj.ActNorm(D)
    x = (
        3.0 * jax.random.normal(jax.random.key(1), (16, T, D))
        + jnp.arange(D, dtype=jnp.float32)
        - 2.0
    )
    new = bj.initialize_from_data(an, x)
    assert float(jnp.max(jnp.abs(an.bias[...]))) == 0.0  # input model untouched
    mean, std = _channel_stats(new.inverse(x))
    np.testing.assert_allclose(mean, 0.0, atol=1e-5)
    np.testing.assert_allclose(std, 1.0, atol=1e-4)
    flat = np.asarray(x).reshape(-1, D)
    close(new.bias[...], -flat.mean(0), tol=1e-5)
    close(new.logs[...], np.log(1.0 / (flat.std(0) + 1e-6)), tol=1e-5)


def test_initialize_in_chain_sees_previous_layers():
    rngs = nnx.Rngs(3)
    lin = perturb(bj.InvertibleLinear(D, rngs=rngs), 2, 0.5)
    chain = bj.Chain.from_data_to_latent([bj.ActNorm(D), lin, bj.ActNorm(D)])
    x = 2.0 * jax.random.normal(jax.random.key(4), (8, T, D)) + 5.0
    new = bj.initialize_from_data(chain, x)
    first, _, last = new.bijectors[2], new.bijectors[1], new.bijectors[0]
    mean, std = _channel_stats(first.inverse(x))
    np.testing.assert_allclose(mean, 0.0, atol=1e-5)
    np.testing.assert_allclose(std, 1.0, atol=1e-4)
    mean, std = _channel_stats(new.inverse(x))  # output of the last ActNorm
    np.testing.assert_allclose(mean, 0.0, atol=1e-5)
    np.testing.assert_allclose(std, 1.0, atol=1e-4)
    assert float(jnp.max(jnp.abs(last.bias[...] - first.bias[...]))) > 1e-3


def test_initialize_constant_channel_is_finite():
    x = jax.random.normal(jax.random.key(5), (4, T, D)).at[..., 1].set(2.5)
    new = bj.initialize_from_data(bj.ActNorm(D), x)
    z, ld = new.inverse_and_log_det(x)
    assert bool(jnp.all(jnp.isfinite(new.logs[...])))
    assert bool(jnp.all(jnp.isfinite(z))) and bool(jnp.all(jnp.isfinite(ld)))
    np.testing.assert_allclose(np.asarray(z[..., 1]), 0.0, atol=1e-4)


def test_initialize_through_inverse():
    """An ActNorm reached forwards (inside Inverse) also normalises its output."""
    x = 3.0 * jax.random.normal(jax.random.key(6), (8, T, D)) - 4.0
    for model in [bj.Inverse(bj.ActNorm(D)), bj.Inverse(bj.Scan(_glow_step, 2, rngs=nnx.Rngs(1)))]:
        ctx = None if isinstance(model.bijector, bj.ActNorm) else jnp.zeros((8, T, C))
        new = bj.initialize_from_data(model, x, context=ctx)
        mean, std = _channel_stats(new.inverse(x, context=ctx))
        np.testing.assert_allclose(mean, 0.0, atol=1e-4)
        np.testing.assert_allclose(std, 1.0, atol=1e-3)


def test_initialize_through_scan_and_custom_model():
    """Scan unrolls in init mode; a user model calling bijectors is initialised as well."""

    def step(rngs):  # the scan acts on squeezed (T/2, 2D) data
        lin = bj.InvertibleLinear(2 * D, rngs=rngs)
        return bj.Chain.from_data_to_latent([lin, bj.ActNorm(2 * D)])

    scan = perturb(bj.Scan(step, K_STEPS, rngs=nnx.Rngs(0)), 1, 0.5)

    class Model(nnx.Module):  # a user model: squeeze, then a Scan, in its own code
        def __init__(self, flow):
            self.flow = flow

        def inverse_and_log_det(self, x, *, context=None):
            return self.flow.inverse_and_log_det(bj.squeeze_time(x), context=context)

    x = 2.0 * jax.random.normal(jax.random.key(2), (8, T, D)) - 1.0
    model = Model(scan)
    new = bj.initialize_from_data(model, x)
    z = new.inverse_and_log_det(x)[0]  # lax.scan path after initialisation
    mean, std = _channel_stats(z)
    np.testing.assert_allclose(mean, 0.0, atol=1e-5)
    np.testing.assert_allclose(std, 1.0, atol=1e-4)
    # every step normalises its own input: check the unrolled chain step by step
    h = bj.squeeze_time(x)
    for k in reversed(range(K_STEPS)):  # data -> latent order
        h = new.flow.step(k).inverse(h)
        mean, std = _channel_stats(h)
        np.testing.assert_allclose(mean, 0.0, atol=1e-5)
        np.testing.assert_allclose(std, 1.0, atol=1e-4)
    # same result as initialising the unrolled chain
    chain_init = bj.initialize_from_data(scan.unrolled(), bj.squeeze_time(x))
    close(chain_init.inverse(bj.squeeze_time(x)), z)
    # the input model is untouched
    old_bias = model.flow.steps.bijectors[0].bias[...]
    close(old_bias, scan.steps.bijectors[0].bias[...], 0)
    assert not np.allclose(old_bias, new.flow.steps.bijectors[0].bias[...])


def test_initialize_inside_jit_is_a_clear_error():
    class Jitted(nnx.Module):
        def __init__(self):
            self.an = bj.ActNorm(D)

        def inverse_and_log_det(self, x, *, context=None):
            return jax.jit(lambda m, x: m.inverse_and_log_det(x))(self.an, x)

    with pytest.raises(ValueError, match="eagerly"):
        bj.initialize_from_data(Jitted(), jnp.ones((2, T, D)))


# ----------------------------------------------------------------------------- Scan


inv = jax.jit(lambda b, x, c: b.inverse_and_log_det(x, context=c))
fwd = jax.jit(lambda b, z, c: b.forward_and_log_det(z, context=c))


def test_scan_equals_chain_values_log_dets_and_grads():
    scan = built("scan")
    chain = scan.unrolled()
    assert len(chain) == K_STEPS
    x, c = data("scan", (3,))
    z_s, ld_s = inv(scan, x, c)
    z_c, ld_c = inv(chain, x, c)
    close(z_s, z_c, 1e-5)
    close(ld_s, ld_c, 1e-5)
    x_s, lf_s = fwd(scan, z_s, c)
    x_c, lf_c = fwd(chain, z_s, c)
    close(x_s, x_c, 1e-5)
    close(lf_s, lf_c, 1e-5)

    def nll(m):
        z, ld = m.inverse_and_log_det(x, context=c)
        return jnp.mean(0.5 * jnp.sum(z**2, axis=(-2, -1)) - ld)

    grad = jax.jit(jax.grad(nll))
    g_scan = nnx.state(grad(scan), nnx.Param)
    g_chain = nnx.state(grad(chain), nnx.Param)
    for k in range(K_STEPS):
        gk = jax.tree.map(lambda a, k=k: a[k], g_scan["steps"])
        for a, b in zip(jax.tree.leaves(gk), jax.tree.leaves(g_chain["bijectors"][k]), strict=True):
            close(a, b, 1e-4)


def test_scan_computes_a_low_precision_input_in_float32():
    """A bfloat16 input to a Scan failed inside lax.scan ("carry input and carry output
    must have equal types": its first ActNorm returns float32); it is now computed in
    float32, the result of the upcast input."""
    scan = built("scan")
    x, c = data("scan", (3,))
    low = x.astype(jnp.bfloat16)
    z, _ = scan.inverse_and_log_det(low, context=c)
    assert z.dtype == jnp.float32
    close(z, scan.inverse_and_log_det(low.astype(jnp.float32), context=c)[0], 1e-6)
    z, _ = scan.inverse_and_log_det(x, context=c)
    back, _ = scan.forward_and_log_det(z.astype(jnp.bfloat16), context=c)
    assert back.dtype == jnp.float32


def test_scan_from_list_and_stacked_module():
    steps = [perturb(_glow_step(nnx.Rngs(i)), i) for i in range(2)]
    scan = bj.Scan(steps)
    chain = bj.Chain(steps)
    x, c = data("scan", (3,))
    close(scan.inverse(x, context=c), chain.inverse(x, context=c), 1e-5)
    again = bj.Scan(scan.steps, 2)
    close(again.forward(x, context=c), chain.forward(x, context=c), 1e-5)
    with pytest.raises(ValueError, match="steps"):
        bj.Scan(scan.steps, 3)


# ----------------------------------------------------------------------------- specifics


def test_invertible_linear_structure():
    lin = bj.InvertibleLinear(D, rngs=nnx.Rngs(0))
    w = lin.weight()
    close(w @ w.T, jnp.eye(D), 1e-5)  # starts orthogonal
    close(jnp.sum(lin.log_s[...]), 0.0, 1e-5)
    params = nnx.state(lin, nnx.Param)
    assert set(params.keys()) == {"lower", "upper", "log_s"}  # P and sign_s are not trained
    fixed = nnx.state(lin, bj.Fixed)
    assert set(fixed.keys()) == {"P", "sign_s"}
    # the masked entries do not matter: W depends only on the strict triangles
    lin2 = perturb(bj.InvertibleLinear(D, rngs=nnx.Rngs(0)), 1)
    w2 = lin2.weight()
    lin2.lower[...] = lin2.lower[...] + jnp.triu(jnp.ones((D, D)))
    lin2.upper[...] = lin2.upper[...] + jnp.tril(jnp.ones((D, D)))
    close(lin2.weight(), w2, 1e-6)
    x = jax.random.normal(jax.random.key(2), (T, D))
    close(lin2.inverse(x), x @ w2.T, 1e-5)
    # gradients never reach the fixed parts
    g = jax.grad(lambda m: jnp.sum(m.inverse(x) ** 2))(lin2)
    assert float(jnp.max(jnp.abs(g.P[...]))) == 0.0


def test_fresh_coupling_is_linear_and_affine_params():
    coup = bj.AffineCoupling(D, coupling_mlp(D, hidden=8, rngs=nnx.Rngs(0)))
    x = jax.random.normal(jax.random.key(0), (2, T, D))
    z, ld = coup.inverse_and_log_det(x)
    s = jax.nn.sigmoid(2.0) + 1e-6
    close(z[..., : D // 2], x[..., : D // 2], 1e-6)
    close(z[..., D // 2 :], x[..., D // 2 :] * s, 1e-6)
    close(ld, jnp.full((2,), T * (D - D // 2) * np.log(s)), 1e-5)
    h = jnp.array([[1.0, -3.0, 0.5, 0.0]])
    shift, scale = bj.affine_params(h)
    close(shift, [[1.0, 0.5]], 1e-7)
    close(scale, jax.nn.sigmoid(jnp.array([[-1.0, 2.0]])) + 1e-6, 1e-7)
    assert bj.coupling_sizes(5) == (2, 3)


def test_coupling_rejects_wrong_conditioner_output():
    bad = MLP(D // 2, 3, hidden=4, rngs=nnx.Rngs(0))  # needs 2 * 3 = 6 outputs
    coup = bj.AffineCoupling(D, bad)
    with pytest.raises(ValueError, match="conditioner must return"):
        coup.inverse(jnp.zeros((T, D)))


def test_squeeze_interleave_order_and_odd_length():
    x = jnp.arange(2 * T * D, dtype=jnp.float32).reshape(2, T, D)
    z = bj.Squeeze().inverse(x)
    assert z.shape == (2, T // 2, 2 * D)
    for t in range(T // 2):
        close(z[:, t], jnp.concatenate([x[:, 2 * t], x[:, 2 * t + 1]], -1), 0)
    with pytest.raises(ValueError, match="divisible"):
        bj.squeeze_time(jnp.zeros((3, D)))


def test_split_merge_odd_channels():
    split = bj.Split(D)
    x = jax.random.normal(jax.random.key(0), (2, T, D))
    kept, factored = split.split(x)
    assert kept.shape == (2, T, 3) and factored.shape == (2, T, 2)
    close(kept, x[..., :3], 0)
    close(split.merge(kept, factored), x, 0)
    with pytest.raises(ValueError, match="expects"):
        split.split(jnp.zeros((T, D + 1)))
    with pytest.raises(ValueError, match="expects"):
        split.merge(factored, kept)
