"""Import of official (StyleGestures) MoGlow weights against a hand-written numpy MoGlow.

The reference below follows the official conventions as documented (channel-first tensors
(B, C, T), layer 0 applied first when normalising, ActNorm (x + bias) * exp(logs), LU 1x1
W = P (l * strict_lower + I) (u * strict_upper + diag(sign_s exp(log_s))), coupling on the
first C//2 channels with h = linear(lstm(cat(z_a, cond))), shift = h[0::2],
scale = sigmoid(h[1::2] + 2) + 1e-6) and is written independently of the JAX model.
"""

from __future__ import annotations

import numpy as np
import pytest

from motionflows.models.moglow import import_stylegestures

D, C, TAU, K, H, LAYERS = 5, 2, 2, 3, 4, 2


def _sigmoid(x):
    return 1.0 / (1.0 + np.exp(-x))


def _official_state_dict(rng):
    na, nb = D // 2, D - D // 2
    cond = TAU * D + (TAU + 1) * C
    sd = {}
    for k in range(K):
        p = f"flow.layers.{k}."
        sd[p + "actnorm.bias"] = rng.normal(size=(1, D, 1))
        sd[p + "actnorm.logs"] = 0.3 * rng.normal(size=(1, D, 1))
        sd[p + "invconv.p"] = np.eye(D)[rng.permutation(D)]
        sd[p + "invconv.sign_s"] = rng.choice([-1.0, 1.0], size=D)
        sd[p + "invconv.l"] = 0.5 * rng.normal(size=(D, D))  # full: only strict lower is used
        sd[p + "invconv.log_s"] = 0.3 * rng.normal(size=D)
        sd[p + "invconv.u"] = 0.5 * rng.normal(size=(D, D))  # only strict upper is used
        for layer in range(LAYERS):
            fan_in = na + cond if layer == 0 else H
            sd[p + f"f.lstm.weight_ih_l{layer}"] = 0.4 * rng.normal(size=(4 * H, fan_in))
            sd[p + f"f.lstm.weight_hh_l{layer}"] = 0.4 * rng.normal(size=(4 * H, H))
            sd[p + f"f.lstm.bias_ih_l{layer}"] = 0.3 * rng.normal(size=4 * H)
            sd[p + f"f.lstm.bias_hh_l{layer}"] = 0.3 * rng.normal(size=4 * H)
        sd[p + "f.linear.weight"] = 0.3 * rng.normal(size=(2 * nb, H))
        sd[p + "f.linear.bias"] = 0.3 * rng.normal(size=2 * nb)
    return {k: np.asarray(v, np.float32) for k, v in sd.items()}


def _np_lstm(seq, sd, p):
    """seq (T, in) -> (T, H): torch.nn.LSTM semantics, zero initial state."""
    out = seq
    for layer in range(LAYERS):
        w_ih, w_hh = sd[p + f"weight_ih_l{layer}"], sd[p + f"weight_hh_l{layer}"]
        b = sd[p + f"bias_ih_l{layer}"] + sd[p + f"bias_hh_l{layer}"]
        h, c, ys = np.zeros(H), np.zeros(H), []
        for x in out:
            g = w_ih @ x + w_hh @ h + b
            i, f, gg, o = (
                _sigmoid(g[:H]),
                _sigmoid(g[H : 2 * H]),
                np.tanh(g[2 * H : 3 * H]),
                _sigmoid(g[3 * H :]),
            )
            c = f * c + i * gg
            h = o * np.tanh(c)
            ys.append(h)
        out = np.stack(ys)
    return out


def _official_log_prob(sd, pose, control):
    """Log-likelihood (nats) of frames TAU..T-1 of one window, in float64, channel-first."""
    sd = {k: v.astype(np.float64) for k, v in sd.items()}
    t_all = pose.shape[0]
    targets = pose[TAU:].T  # (C, T')  channel-first, as the official code holds data
    cond = np.stack(
        [
            np.concatenate([pose[t - TAU : t].reshape(-1), control[t - TAU : t + 1].reshape(-1)])
            for t in range(TAU, t_all)
        ],
        axis=1,
    )  # (cond, T')
    n_t = targets.shape[1]
    z, logdet = targets.copy(), 0.0
    lower = np.tril(np.ones((D, D)), -1)
    for k in range(K):  # official order: layer 0 first in the normalising direction
        p = f"flow.layers.{k}."
        z = (z + sd[p + "actnorm.bias"][0]) * np.exp(sd[p + "actnorm.logs"][0])
        logdet += n_t * sd[p + "actnorm.logs"].sum()
        w = (
            sd[p + "invconv.p"]
            @ (sd[p + "invconv.l"] * lower + np.eye(D))
            @ (
                sd[p + "invconv.u"] * lower.T
                + np.diag(sd[p + "invconv.sign_s"] * np.exp(sd[p + "invconv.log_s"]))
            )
        )
        z = w @ z
        logdet += n_t * sd[p + "invconv.log_s"].sum()
        za, zb = z[: D // 2], z[D // 2 :]
        y = _np_lstm(np.concatenate([za, cond], 0).T, sd, p + "f.lstm.")  # (T', H)
        h = (y @ sd[p + "f.linear.weight"].T + sd[p + "f.linear.bias"]).T  # (2nb, T')
        shift, scale = h[0::2], _sigmoid(h[1::2] + 2.0) + 1e-6
        zb = (zb + shift) * scale
        logdet += np.log(scale).sum()
        z = np.concatenate([za, zb], 0)
    return logdet - 0.5 * np.sum(z**2 + np.log(2 * np.pi))


def test_import_reproduces_hand_computed_log_prob():
    rng = np.random.default_rng(0)
    sd = _official_state_dict(rng)
    model = import_stylegestures(sd, pose_dim=D, control_dim=C, tau=TAU)
    assert model.num_steps == K and model.hidden == H and model.num_layers == LAYERS
    pose = rng.normal(size=(2, 7, D)).astype(np.float32)
    control = rng.normal(size=(2, 7, C)).astype(np.float32)
    got = np.asarray(model.log_prob(pose, control))
    want = np.array([_official_log_prob(sd, pose[b], control[b]) for b in range(2)])
    np.testing.assert_allclose(got, want, rtol=2e-5, atol=2e-4)

    # torch-like objects (with .detach().cpu().numpy()) are accepted too
    class FakeTensor:
        def __init__(self, a):
            self.a = a

        def detach(self):
            return self

        def cpu(self):
            return self

        def numpy(self):
            return self.a

    model2 = import_stylegestures(
        {k: FakeTensor(v) for k, v in sd.items()}, pose_dim=D, control_dim=C, tau=TAU
    )
    np.testing.assert_allclose(np.asarray(model2.log_prob(pose, control)), got, rtol=1e-6)


def test_import_rejects_wrong_sizes_and_missing_entries():
    sd = _official_state_dict(np.random.default_rng(1))
    with pytest.raises(ValueError, match="weight_ih_l0"):
        import_stylegestures(sd, pose_dim=D, control_dim=C, tau=TAU + 1)
    bad = {k: v for k, v in sd.items() if not k.endswith("invconv.log_s")}
    with pytest.raises(ValueError, match="invconv.log_s"):
        import_stylegestures(bad, pose_dim=D, control_dim=C, tau=TAU)
    with pytest.raises(ValueError, match="graph"):
        import_stylegestures({"foo": np.zeros(3)}, pose_dim=D, control_dim=C, tau=TAU)
