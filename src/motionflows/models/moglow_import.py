"""Import official StyleGestures MoGlow checkpoints into :class:`~motionflows.models.moglow.MoGlow`.

The official code (github.com/simonalexanderson/StyleGestures, academic licence) stores a
PyTorch state dict; :func:`import_stylegestures` maps its entries onto a MoGlow built with
the same sizes, and :func:`load_stylegestures_checkpoint` reads the ``.pkg``/``.pt`` file
first (needs torch). Both are re-exported by :mod:`motionflows.models.moglow`.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import jax.numpy as jnp
import numpy as np
from flax import nnx

from motionflows.bijectors import coupling_sizes
from motionflows.data.names import CONTROL_DIM, POSE_DIM

if TYPE_CHECKING:
    from motionflows.models.moglow import MoGlow

__all__ = ["import_stylegestures", "load_stylegestures_checkpoint"]


def _np(state_dict: dict, name: str) -> np.ndarray:
    if name not in state_dict:
        raise ValueError(f"import_stylegestures: the state dict has no entry {name!r}")
    value = state_dict[name]
    if hasattr(value, "detach"):  # a torch tensor
        value = value.detach().cpu().numpy()
    return np.asarray(value, np.float32)


def _layer_count(state_dict: dict, prefix: str) -> int:
    """The number of official flow layers: consecutive ``<prefix><k>.`` entries from 0."""
    layer_ids = sorted(
        {
            int(name[len(prefix) :].split(".")[0])
            for name in state_dict
            if name.startswith(prefix) and name[len(prefix) :].split(".")[0].isdigit()
        }
    )
    if not layer_ids or layer_ids != list(range(len(layer_ids))):
        raise ValueError(
            f"import_stylegestures: found no consecutive '{prefix}<k>.' entries (got layers "
            f"{layer_ids}); pass the checkpoint's 'graph' state dict"
        )
    return len(layer_ids)


def _lstm_sizes(
    state_dict: dict, prefix: str, pose_dim: int, control_dim: int, tau: int
) -> tuple[int, int]:
    """(hidden, num_layers) of the official LSTM, its input width checked against the sizes."""
    first = f"{prefix}0.f."
    hidden = _np(state_dict, first + "lstm.weight_hh_l0").shape[1]
    num_layers = len([n for n in state_dict if n.startswith(first + "lstm.weight_hh_l")])
    na, nb = coupling_sizes(pose_dim)
    cond_dim = tau * pose_dim + (tau + 1) * control_dim
    w_ih0 = _np(state_dict, first + "lstm.weight_ih_l0")
    if w_ih0.shape != (4 * hidden, na + cond_dim):
        raise ValueError(
            f"import_stylegestures: {first}lstm.weight_ih_l0 has shape {w_ih0.shape}, expected "
            f"(4*{hidden}, {na} + {cond_dim}) for pose_dim={pose_dim}, control_dim="
            f"{control_dim}, tau={tau}; pass the values the checkpoint was trained with"
        )
    return hidden, num_layers


def _step_arrays(state_dict: dict, n: str, pose_dim: int, num_layers: int) -> dict:
    """One official layer's arrays (names starting with ``n``) in this model's layout."""
    lower_mask = np.tril(np.ones((pose_dim, pose_dim), np.float32), -1)
    upper_mask = lower_mask.T

    def g(name):
        return _np(state_dict, n + name)

    arrays = {
        "bias": g("actnorm.bias").reshape(pose_dim),
        "logs": g("actnorm.logs").reshape(pose_dim),
        "P": g("invconv.p"),
        "sign_s": g("invconv.sign_s").reshape(pose_dim),
        "lower": g("invconv.l") * lower_mask,
        "upper": g("invconv.u") * upper_mask,
        "log_s": g("invconv.log_s").reshape(pose_dim),
        "w_out": g("f.linear.weight").T,
        "b_out": g("f.linear.bias"),
    }
    for layer in range(num_layers):
        arrays[f"w_ih{layer}"] = g(f"f.lstm.weight_ih_l{layer}").T
        arrays[f"w_hh{layer}"] = g(f"f.lstm.weight_hh_l{layer}").T
        arrays[f"b_ih{layer}"] = g(f"f.lstm.bias_ih_l{layer}")
        arrays[f"b_hh{layer}"] = g(f"f.lstm.bias_hh_l{layer}")
    return arrays


def _put(var, value) -> None:
    """Write ``value`` into the variable ``var``, refusing a shape mismatch."""
    if tuple(var.shape) != value.shape:
        raise ValueError(
            f"import_stylegestures: shape mismatch {value.shape} vs expected {var.shape}"
        )
    var[...] = jnp.asarray(value)


def _load_steps(model: MoGlow, stacked: dict) -> None:
    """Write the stacked per-step arrays into the model's scanned flow steps."""
    coupling, linear, actnorm = model.flow.steps.bijectors
    net = coupling.conditioner
    _put(actnorm.bias, stacked["bias"])
    _put(actnorm.logs, stacked["logs"])
    _put(linear.P, stacked["P"])
    _put(linear.sign_s, stacked["sign_s"])
    _put(linear.lower, stacked["lower"])
    _put(linear.upper, stacked["upper"])
    _put(linear.log_s, stacked["log_s"])
    _put(net.w_out, stacked["w_out"])
    _put(net.b_out, stacked["b_out"])
    for layer, mod in enumerate(net.lstm.layers):
        _put(mod.w_ih, stacked[f"w_ih{layer}"])
        _put(mod.w_hh, stacked[f"w_hh{layer}"])
        _put(mod.b_ih, stacked[f"b_ih{layer}"])
        _put(mod.b_hh, stacked[f"b_hh{layer}"])


def import_stylegestures(
    state_dict: dict,
    *,
    pose_dim: int = POSE_DIM,
    control_dim: int = CONTROL_DIM,
    tau: int = 10,
    prefix: str = "flow.layers.",
    compute_dtype: str | None = None,
    eps: float = 1e-6,
) -> MoGlow:
    """A :class:`MoGlow` holding the weights of an official StyleGestures MoGlow checkpoint.

    ``state_dict`` maps the official parameter names (the checkpoint's "graph" entry) to
    arrays (numpy or torch). K, the LSTM width and depth are read from the shapes. Official
    conventions and how they map here (step k of ours = official layer K-1-k):

    * ``actnorm.bias``/``logs`` (1, C, 1) -> ActNorm ``bias``/``logs`` (C,): both compute
      (x + bias) * exp(logs) in the normalising direction.
    * ``invconv.p``, ``sign_s``, ``l`` (strictly-lower part), ``log_s``, ``u`` (strictly-upper
      part) -> ``P``, ``sign_s``, ``lower``, ``log_s``, ``upper``: the same
      W = P (L' + I) (U' + diag(sign_s exp(log_s))), z_t = W x_t.
    * ``f.lstm.weight_ih_l{n}`` (4H, in) etc. -> ``w_ih`` (in, 4H) (transposed), gate order
      i, f, g, o in both; the LSTM input is [z_a, cond_t].
    * ``f.linear.weight`` (2|b|, H), ``bias`` -> ``w_out`` (H, 2|b|), ``b_out``.
    """
    if not isinstance(state_dict, dict):
        raise ValueError("import_stylegestures expects a dict of parameter name -> array")
    k_steps = _layer_count(state_dict, prefix)
    hidden, num_layers = _lstm_sizes(state_dict, prefix, pose_dim, control_dim, tau)
    from motionflows.models.moglow import MoGlow  # moglow re-exports this module

    model = MoGlow(
        pose_dim,
        control_dim,
        tau=tau,
        K=k_steps,
        hidden=hidden,
        num_layers=num_layers,
        compute_dtype=compute_dtype,
        eps=eps,
        rngs=nnx.Rngs(0),
    )
    per_step = [
        _step_arrays(state_dict, f"{prefix}{k_steps - 1 - k}.", pose_dim, num_layers)
        for k in range(k_steps)
    ]
    stacked = {name: np.stack([s[name] for s in per_step]) for name in per_step[0]}
    _load_steps(model, stacked)
    return model


def load_stylegestures_checkpoint(path: str, **kwargs) -> MoGlow:
    """Read an official StyleGestures ``.pkg``/``.pt`` checkpoint (needs torch) and import it.

    The checkpoint's ``"graph"`` entry (or the file itself, if it is a state dict) is
    passed to :func:`import_stylegestures` with ``kwargs``. The file is read with
    ``torch.load(..., weights_only=True)``: tensors and plain containers only, so loading
    never runs code from the file. A file that needs more (a pickled module or optimiser
    object) is refused with the reason; it is never loaded unsafely.
    """
    try:
        import torch  # noqa: PLC0415
    except ImportError as err:  # pragma: no cover - depends on the environment
        raise ImportError(
            "load_stylegestures_checkpoint needs PyTorch to read the .pt/.pkg file: "
            "pip install torch (CPU build is enough), or pass a dict of numpy arrays to "
            "import_stylegestures"
        ) from err
    try:
        data = torch.load(path, map_location="cpu", weights_only=True)
    except FileNotFoundError:
        raise ValueError(f"{path}: file not found") from None
    except Exception as err:  # torch's UnpicklingError and friends
        reason = str(err).strip().splitlines()[0] if str(err).strip() else type(err).__name__
        raise ValueError(
            f"{path}: cannot be read safely with torch.load(weights_only=True) ({reason}). "
            "motionflows does not load checkpoints that may run code; re-save the weights "
            "alone, e.g. torch.save(checkpoint['graph'], 'graph.pt') in the environment that "
            "wrote it, or pass a dict of numpy arrays to import_stylegestures"
        ) from None
    state = data.get("graph", data) if isinstance(data, dict) else data
    if not isinstance(state, dict):
        raise ValueError(
            f"{path}: expected a state dict (parameter name -> tensor) or a dict with a "
            f"'graph' state dict, got {type(state).__name__}"
        )
    return import_stylegestures(dict(state), **kwargs)
