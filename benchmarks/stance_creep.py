"""Does a MoGlow's stance foot creep in one step, or only when it runs on its own output?

Teacher forcing: for each target frame t of real windows (the official scope, frames
tau..T-1), the model gets the real history x_{t-tau..t-1} and the real controls and draws
frame t once (latent ``temperature * eps``; 0 = the mode). On the steps t-1 -> t where the
real foot stands (the calibrated contact rule, at both frames), the foot centre (mean of
ankle and toe) moves in the world from the *real* frame t-1 to the *drawn* frame t; this
prints its mean horizontal speed (m/s, the one-step foot sliding) and its mean component
along the root's facing (m/s, + = forward: the creep), beside the same for the real frame t
and the free-running sample's foot sliding on the same windows (the bench's metric).

If the one-step creep is as large as the free-running one, the model's conditional
distribution itself puts the stance foot ahead (a learning problem); if it is small,
the creep builds up from the model's own history (exposure bias).

For the takes ``--takes`` (default: every Bandai take of the performer D2-C, as
``foot_heights.py``) cut into 4 s windows at 20 fps::

    python benchmarks/stance_creep.py pretrained:moglow-bandai RUN_DIR ...
"""

from __future__ import annotations

import argparse
import glob
import json
import os
import platform
import sys

import jax
import jax.numpy as jnp
import numpy as np

from motionflows.data.features import clip_from_bvh, integrate_root
from motionflows.data.names import FOOT_JOINTS, NUM_JOINTS
from motionflows.data.pipeline import make_windows
from motionflows.errors import RunError
from motionflows.evaluation.motion import foot_contacts, foot_sliding, to_global
from motionflows.models.moglow import MoGlow
from motionflows.pretrained.model import PretrainedModel
from motionflows.runs import resolve_run_dir

SHARED = os.path.join(os.path.dirname(__file__), "..", "..", "shared", "data")
DEFAULT_TAKES = (  # the performer D2-C: the masculine and normal styles of dataset 2
    f"{SHARED}/bandai_locomotion_*/dataset-2_*_masculine_*.bvh",
    f"{SHARED}/bandai_locomotion_*/dataset-2_*_normal_*.bvh",
)
FPS, WINDOW, HOP = 20.0, 80, 40


def one_step(model: MoGlow, pose_std, control_std, key, temperature: float) -> jax.Array:
    """Frame t drawn from the real history and controls, for every official target frame:
    (B, T - tau, D), standardised."""
    targets, cond, previous = model.conditions(pose_std, control_std, scope="official")
    z = temperature * model.base_density().sample(key, targets.shape[:-1])
    u = model._steps().forward(z, context=cond)  # the K steps as the model runs them
    if not model.residual:
        return u
    return model._difference().forward_step(u, context_t=cond, carry=previous)[0]


def stance_steps(pose, drawn, control, tau: int, *, fps: float) -> dict:
    """The foot centre's world step from real frame t-1 to frame t of ``drawn`` (B, T, 63,
    frames < tau are the real ones) on the real stance steps: mean speed and forward part."""
    feet = (FOOT_JOINTS[:2], FOOT_JOINTS[2:])

    def centres(p):
        w = to_global(p, control).reshape(p.shape[:-1] + (NUM_JOINTS, 3))
        return np.stack([0.5 * (w[..., a, :] + w[..., b, :]) for a, b in feet], axis=-2)

    real, new = centres(pose), centres(drawn)
    contact = foot_contacts(pose)
    stand = (contact[:, tau - 1 : -1] & contact[:, tau:]).transpose(0, 2, 1)  # (B, 2, T')
    step = (new[:, tau:] - real[:, tau - 1 : -1]).transpose(0, 2, 1, 3)  # (B, 2, T', 3)
    yaw = integrate_root(control)[1]
    facing = np.stack([np.sin(yaw), np.cos(yaw)], -1)[:, None, tau:]  # (B, 1, T', 2)
    speed = np.hypot(step[..., 0], step[..., 2]) * fps
    forward = np.sum(step[..., [0, 2]] * facing, -1) * fps
    return {
        "stance_steps": int(stand.sum()),
        "speed_m_s": round(float(speed[stand].mean()), 4),
        "forward_m_s": round(float(forward[stand].mean()), 4),
    }


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("runs", nargs="*", help="MoGlow run directories or pretrained:NAME")
    p.add_argument("--takes", action="append", help="glob of BVH takes (repeatable)")
    p.add_argument("--windows", type=int, default=256, help="at most this many windows")
    p.add_argument("--temperatures", default="0,0.8")
    p.add_argument("--seed", type=int, default=0)
    args = p.parse_args(argv)
    files = sorted({f for g in (args.takes or DEFAULT_TAKES) for f in glob.glob(g)})
    if not files:
        print(f"stance_creep: no BVH take matches {args.takes or DEFAULT_TAKES}; pass --takes "
              "'DIR/*.bvh' (the Bandai set: motionflows data download bandai)",
              file=sys.stderr)  # fmt: skip
        return 2
    models = []
    for spec in args.runs:
        try:
            m = PretrainedModel.from_run(resolve_run_dir(spec))
        except RunError as e:
            print(f"stance_creep: {e}", file=sys.stderr)
            return 2
        if not isinstance(m.model, MoGlow):
            print(f"stance_creep: {spec} is a {m.name}, not a MoGlow", file=sys.stderr)
            return 2
        models.append((spec, m))
    cut, _ = make_windows([clip_from_bvh(f, FPS) for f in files], WINDOW, HOP, short="drop")
    pick = np.linspace(0, len(cut.pose) - 1, min(args.windows, len(cut.pose))).round().astype(int)
    pose = np.asarray(cut.pose, np.float64)[pick]
    control = np.asarray(cut.control, np.float64)[pick]
    print(json.dumps({"takes": len(files), "windows": len(pick), "fps": FPS, "window": WINDOW,
                      "machine": platform.processor() or platform.machine(),
                      "load_average": os.getloadavg()[0]}))  # fmt: skip
    for spec, m in models:
        tau, std = m.model.tau, m.standardizer
        row = {"source": spec, "tau": tau, "real": stance_steps(pose, pose, control, tau, fps=FPS)}
        p_std = jnp.asarray(std.normalize_pose(pose.astype(np.float32)))
        c_std = jnp.asarray(std.normalize_control(control.astype(np.float32)))
        draw = jax.jit(one_step, static_argnames="temperature")
        for t in (float(x) for x in args.temperatures.split(",")):
            x = np.asarray(draw(m.model, p_std, c_std, jax.random.key(args.seed), temperature=t))
            drawn = pose.copy()
            drawn[:, tau:] = std.denormalize_pose(x)
            sample = np.asarray(m.sample(control, seed=args.seed, temperature=t), np.float64)
            row[f"T{t:g}"] = {
                "one_step": stance_steps(pose, drawn, control, tau, fps=FPS),
                "free_running_foot_sliding": round(foot_sliding(sample, control, fps=FPS), 4),
            }
        print(json.dumps(row), flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
