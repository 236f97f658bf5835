"""Procedural locomotion on the 21-joint skeleton: the embedded, download-free default.

Each clip is driven by a random control trajectory (standing, walking 0.5-1.8 m/s, running
2-3.5 m/s with walk-run transitions, walking backwards, sidestepping, turning) and a
random per-clip style (body scale, stride, step width, arm swing, elbow bend, posture lean,
bob, sway). The body is built in world coordinates at 30 fps:

* a gait phase ``phi`` whose rate (strides/s) follows the speed (walk ``0.45 + 0.4 v``,
  run ``1.2 + 0.12 v``, blended by a smooth walk-run weight), frozen when standing;
* per foot (left ``phi``, right ``phi + 1/2``) a stance fraction (0.62 walking, 0.38
  running). A footprint is placed beside the planned root at mid-stance; during stance the
  foot is planted (the toe stays fixed while the heel lifts at the end), during swing it
  moves to the next footprint on an arc. No foot sliding in the ground truth;
* pelvis = root + lateral sway + vertical bob (high at mid-stance when walking, low when
  running), lowered where a leg could not reach; knees from two-bone IK bending forward;
* spine leaning with speed and style, arms counter-swinging with the opposite leg, elbows
  bending more when running; small smooth noise on the upper body.

The world positions then go through :func:`motionflows.data.features.features_from_positions`,
the same code as real BVH data, so the synthetic controls are *measured*, not planned.
Deterministic in ``seed``; about 20 minutes of motion take a few seconds.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from motionflows.data.features import (
    ROOT_SIGMA_S,
    Clip,
    features_from_positions,
    gaussian_smooth,
    rotate_y,
)
from motionflows.data.names import DEFAULT_FPS, JOINT_NAMES, NUM_JOINTS

SRC_FPS = 30.0
MODES = ("stand", "walk", "run", "back", "sidestep")
_MODE_P = np.array([0.1, 0.38, 0.24, 0.12, 0.16])
_J = {n: i for i, n in enumerate(JOINT_NAMES)}


def _smoothstep(x):
    x = np.clip(x, 0.0, 1.0)
    return x * x * (3.0 - 2.0 * x)


def random_style(rng: np.random.Generator) -> dict:
    """Per-clip style parameters."""
    return dict(
        scale=rng.uniform(0.93, 1.07),
        stride=rng.uniform(0.85, 1.15),
        width=rng.uniform(0.07, 0.12),
        arm=rng.uniform(0.3, 1.0),
        elbow=rng.uniform(0.3, 0.8),
        lean=rng.uniform(-0.05, 0.2),
        bob=rng.uniform(0.6, 1.4),
        sway=rng.uniform(0.01, 0.035),
        lift=rng.uniform(0.05, 0.12),
        run_speed=rng.uniform(1.7, 2.1),
        abduct=rng.uniform(0.12, 0.35),
        noise=rng.uniform(0.002, 0.008),
    )


def random_controls(rng: np.random.Generator, n: int, fps: float) -> np.ndarray:
    """(n, 3) planned (forward m/s, sideways m/s, turn rad/s): random smoothed segments."""
    target = np.zeros((n, 3))
    t = 0
    while t < n:
        length = int(rng.uniform(1.5, 4.5) * fps)
        mode = MODES[rng.choice(len(MODES), p=_MODE_P)]
        fwd = side = turn = 0.0
        if mode == "walk":
            fwd = rng.uniform(0.5, 1.8)
        elif mode == "run":
            fwd = rng.uniform(2.0, 3.5)
        elif mode == "back":
            fwd = -rng.uniform(0.4, 1.1)
        elif mode == "sidestep":
            side = rng.choice([-1.0, 1.0]) * rng.uniform(0.3, 0.8)
            fwd = rng.uniform(-0.1, 0.3)
        if mode in ("walk", "run") and rng.uniform() < 0.5:
            turn = rng.choice([-1.0, 1.0]) * rng.uniform(0.3, 1.3) / (1.0 + 0.3 * abs(fwd))
        elif mode == "stand" and rng.uniform() < 0.3:
            turn = rng.choice([-1.0, 1.0]) * rng.uniform(0.3, 0.8)
        target[t : t + length] = (fwd, side, turn)
        t += length
    return gaussian_smooth(target, 0.35 * fps)


_LEGS = (
    ("LeftUpLeg", "LeftLeg", "LeftFoot", "LeftToe"),
    ("RightUpLeg", "RightLeg", "RightFoot", "RightToe"),
)
_ARMS = (
    ("LeftArm", "LeftForeArm", "LeftHand", "LeftHandIndex"),
    ("RightArm", "RightForeArm", "RightHand", "RightHandIndex"),
)


@dataclasses.dataclass(frozen=True)
class _Plan:
    """Per-frame signals that drive one clip of ``n`` frames at SRC_FPS (arrays are (n,)
    unless noted)."""

    n: int
    sc: float  # body scale
    fwd_v: np.ndarray  # planned forward velocity (m/s)
    side_v: np.ndarray  # planned sideways velocity (m/s)
    speed: np.ndarray  # hypot(fwd_v, side_v)
    yaw: np.ndarray  # heading (rad)
    root: np.ndarray  # (n, 3) planned root on the ground (m)
    run: np.ndarray  # walk-run weight in [0, 1]
    active: np.ndarray  # stepping weight in [0, 1] (0: standing still)
    phi: np.ndarray  # gait phase (strides)
    beta: np.ndarray  # stance fraction of a stride


def _plan(rng: np.random.Generator, n: int, style: dict, planned: np.ndarray) -> _Plan:
    """Integrate the (n, 3) planned controls into heading, root path and gait phase.

    ``yaw`` and ``root`` are Euler sums of the turn rate and the rotated velocity from a
    random start; ``phi`` integrates the stride rate (walk/run blend of the cadences, times
    ``active``); ``beta`` blends the walking and running stance fractions.
    """
    dt = 1.0 / SRC_FPS
    sc = style["scale"]
    fwd_v, side_v, turn_v = planned[:, 0], planned[:, 1], planned[:, 2]
    speed = np.hypot(fwd_v, side_v)

    yaw = rng.uniform(-np.pi, np.pi) + np.concatenate([[0.0], np.cumsum(turn_v[:-1] * dt)])
    vel = rotate_y(np.stack([side_v, np.zeros(n), fwd_v], -1), yaw)
    root = rng.uniform(-2, 2, 3) * np.array([1, 0, 1]) + np.concatenate(
        [np.zeros((1, 3)), np.cumsum(vel[:-1] * dt, axis=0)]
    )

    run = _smoothstep((speed - style["run_speed"] + 0.25) / 0.5)
    # turning on the spot also makes the feet step (pivoting around the root)
    active = _smoothstep(np.hypot(speed, 0.4 * turn_v) / 0.35)
    # strides/s; walking strides are capped at 1.45 m (times scale and style) so a fast walk
    # quickens its cadence instead of over-reaching
    cap = 1.45 * sc * style["stride"]
    f_walk = np.maximum((0.55 + 0.38 * speed) / style["stride"], speed / cap)
    f_run = (1.2 + 0.15 * speed) / style["stride"]
    freq = (1 - run) * f_walk + run * f_run
    rate = freq * active + 1e-4
    phi = rng.uniform() + np.concatenate([[0.0], np.cumsum(rate[:-1] * dt)])
    beta_walk = 0.62 - 0.07 * np.clip(speed - 1.0, 0, 1)
    beta = (1 - run) * beta_walk + run * (0.38 - 0.04 * np.clip(speed - 2.5, 0, 1))
    return _Plan(n, sc, fwd_v, side_v, speed, yaw, root, run, active, phi, beta)


def _toe_of(
    ankle: np.ndarray, yaw_f: np.ndarray, pitch: np.ndarray, foot_vec: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Toe (n, 3) of a foot at ``ankle`` with heading ``yaw_f`` pitched by ``pitch`` (rad),
    and the (n, 3) ankle->toe vector ``foot_vec`` rotated by the pitch about the foot's x."""
    c, s = np.cos(pitch), np.sin(pitch)
    d = np.stack(
        [
            np.zeros_like(c),
            foot_vec[1] * c - foot_vec[2] * s,
            foot_vec[1] * s + foot_vec[2] * c,
        ],
        -1,
    )
    return ankle + rotate_y(d, yaw_f), d


def _footprints(
    p: _Plan, style: dict, side: float, pf: np.ndarray, cycles: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Footprints of one foot (``side`` +1 left, -1 right; phase ``pf``) for gait cycles
    ``cycles`` (K,): (K, 3) ankle positions beside the root at mid-stance, (K,) their yaw and
    (K,) the stance fraction of each cycle."""
    tgrid = np.arange(p.n, dtype=np.float64)
    # mid-stance time of each cycle (phase is strictly increasing)
    tmid = np.interp(cycles + 0.25, pf, tgrid)
    bmid = np.interp(tmid, tgrid, p.beta)
    tmid = np.interp(cycles + 0.5 * bmid, pf, tgrid)
    rmid = np.stack([np.interp(tmid, tgrid, p.root[:, i]) for i in range(3)], -1)
    ymid = np.interp(tmid, tgrid, p.yaw)
    w = style["width"] * p.sc
    # feet land a little behind the hips, more so when running (as in mocap)
    rmid_run = np.interp(tmid, tgrid, p.run)
    back = -(0.05 + 0.03 * rmid_run) * p.sc
    ankle_h = 0.095 * p.sc
    local = np.stack([side * w * np.ones_like(back), ankle_h * np.ones_like(back), back], -1)
    return rmid + rotate_y(local, ymid), ymid, bmid


def _foot(
    p: _Plan, style: dict, side: float, offset: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """One foot (``side`` +1 left, -1 right; phase ``phi + offset``): (n, 3) ankle, (n, 3)
    toe and (n, 3) forward direction. Planted during stance (the toe stays fixed while the
    heel lifts at the end), on an arc to the next footprint during swing."""
    n, run, active = p.n, p.run, p.active
    foot_vec = np.array([0.0, -0.065 * p.sc, 0.097 * p.sc])  # ankle -> toe, foot frame
    pf = p.phi + offset
    k = np.floor(pf)
    u = pf - k
    kmin, kmax = int(k.min()), int(k.max()) + 1
    cycles = np.arange(kmin, kmax + 1, dtype=np.float64)
    prints, ymid, bmid = _footprints(p, style, side, pf, cycles)
    idx = (k - kmin).astype(np.int64)
    a_now, a_next = prints[idx], prints[idx + 1]
    y_now, y_next = ymid[idx], ymid[idx + 1]
    lift = style["lift"] * (1 + 0.6 * run) * active
    pitch_max = (0.35 + 0.25 * run) * active

    beta_c = bmid[idx]  # one stance fraction per cycle, as used to place its footprint
    stance = u < beta_c
    # stance: flat, then heel-off rotating about the planted toe
    heel = _smoothstep((u / np.maximum(beta_c, 1e-6) - 0.6) / 0.4) * pitch_max
    toe_fixed, _ = _toe_of(a_now, y_now, np.zeros(n), foot_vec)
    _, d_h = _toe_of(a_now, y_now, heel, foot_vec)
    ankle_st = toe_fixed - rotate_y(d_h, y_now)
    # swing: from the lift-off ankle to the next footprint
    s = np.clip((u - beta_c) / np.maximum(1 - beta_c, 1e-6), 0, 1)
    _, d_lo = _toe_of(a_now, y_now, pitch_max, foot_vec)
    lo = toe_fixed - rotate_y(d_lo, y_now)
    e = _smoothstep(s)[:, None]
    ankle_sw = lo + (a_next - lo) * e
    kick = 0.22 * run * active * np.sin(np.pi * s**0.6)  # running heel kick, early
    ankle_sw[:, 1] = (1 - s) * lo[:, 1] + s * a_next[:, 1] + lift * np.sin(np.pi * s) + kick
    yaw_sw = y_now + (y_next - y_now) * e[:, 0]
    pitch_sw = pitch_max * (1 - s) ** 2 - 0.25 * active * np.sin(np.pi * s) ** 2 * s
    ankle = np.where(stance[:, None], ankle_st, ankle_sw)
    yaw_f = np.where(stance, y_now, yaw_sw)
    pitch = np.where(stance, heel, pitch_sw)
    toe, _ = _toe_of(ankle, yaw_f, pitch, foot_vec)
    return ankle, toe, rotate_y(np.array([0.0, 0.0, 1.0]), yaw_f)


def _pelvis(
    rng: np.random.Generator, p: _Plan, style: dict
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """(n, 3) pelvis = root + lateral sway + surge + lean offset (its height is set by
    :func:`_place_legs`), with (n,) nominal hip height (m, with bob), lean (rad, forward
    with speed and acceleration) and twist (rad, with the stride)."""
    n, sc, run, active, speed = p.n, p.sc, p.run, p.active, p.speed
    fwd_v, side_v, phi = p.fwd_v, p.side_v, p.phi
    ph = 2 * np.pi * (phi - p.beta / 2)
    sway = style["sway"] * active * (1 - 0.5 * run) * np.cos(ph)
    bob = style["bob"] * active * ((1 - run) * 0.018 * np.cos(2 * ph) - run * 0.03 * np.cos(2 * ph))
    hip_nom = (0.905 * sc - 0.025 * run - 0.006 * speed) + bob
    lean = style["lean"] + 0.05 * np.clip(fwd_v, -1.5, 3.5) + rng.normal(0, 0.02)
    acc = np.gradient(gaussian_smooth(fwd_v, 0.2 * SRC_FPS)) * SRC_FPS
    lean = gaussian_smooth(lean + 0.05 * np.clip(acc, -2, 2), 0.1 * SRC_FPS)
    twist = 0.08 * active * np.sin(2 * np.pi * phi) * np.minimum(speed, 2.0) / 2.0
    # surge: the hips are slowest at mid-stance (inverted pendulum), fastest in double support
    surge = -0.025 * style["bob"] * active * (1 - 0.5 * run) * np.sin(2 * ph)
    travel = np.stack([side_v, fwd_v], -1) / np.maximum(speed, 1e-6)[:, None]
    offset = np.stack(
        [sway + surge * travel[:, 0], np.zeros(n), -0.03 * lean + surge * travel[:, 1]], -1
    )
    return p.root + rotate_y(offset, p.yaw), hip_nom, lean, twist


def _knee(
    hip: np.ndarray, ankle: np.ndarray, ffwd: np.ndarray, thigh: float, shin: float
) -> tuple[np.ndarray, np.ndarray]:
    """Two-bone IK: the (n, 3) ankle pulled within reach of ``hip`` and the (n, 3) knee,
    bent towards the foot's forward direction ``ffwd`` (law of cosines on the thigh)."""
    d = ankle - hip
    dist = np.linalg.norm(d, axis=-1, keepdims=True)
    uvec = d / np.maximum(dist, 1e-9)
    dist = np.clip(dist, 0.2, 0.999 * (thigh + shin))
    ankle = hip + uvec * dist  # reaches (clamped only in rare overshoots)
    cos_a = np.clip((thigh**2 + dist**2 - shin**2) / (2 * thigh * dist), -1, 1)
    pole = ffwd - np.sum(ffwd * uvec, -1, keepdims=True) * uvec
    pole /= np.maximum(np.linalg.norm(pole, axis=-1, keepdims=True), 1e-9)
    return ankle, hip + thigh * (cos_a * uvec + np.sqrt(1 - cos_a**2) * pole)


def _place_legs(
    out: np.ndarray,
    p: _Plan,
    pelvis: np.ndarray,
    hip_nom: np.ndarray,
    twist: np.ndarray,
    feet: list[tuple[np.ndarray, np.ndarray, np.ndarray]],
) -> None:
    """Lower the pelvis (in place) where a leg could not reach its ankle, then write the
    hips, upper legs, knees, ankles and toes of ``feet`` (ankle, toe, forward) into the
    (n, 21, 3) ``out``."""
    n, sc = p.n, p.sc
    thigh, shin = 0.391 * sc, 0.410 * sc
    hip_w, hip_drop = 0.065 * sc, 0.023 * sc
    reach = 0.995 * (thigh + shin)
    hip_y = hip_nom
    hipj = []
    for side, (ankle, _, _) in zip((1.0, -1.0), feet, strict=True):
        local = np.stack([side * hip_w * np.ones(n), np.zeros(n), np.zeros(n)], -1)
        hj = pelvis + rotate_y(local, (p.yaw + twist))
        dh2 = np.sum((ankle - hj)[:, [0, 2]] ** 2, -1)
        ymax = ankle[:, 1] + np.sqrt(np.maximum(reach**2 - dh2, 0.01)) + hip_drop
        hip_y = np.minimum(hip_y, ymax)
        hipj.append(hj)
    hip_y = np.maximum(gaussian_smooth(hip_y, 0.7), 0.84 * hip_nom)
    pelvis[:, 1] = hip_y
    out[:, _J["Hips"]] = pelvis
    for hj, (ankle, toe, ffwd), names in zip(hipj, feet, _LEGS, strict=True):
        hj = hj.copy()
        hj[:, 1] = hip_y - hip_drop
        ankle, knee = _knee(hj, ankle, ffwd, thigh, shin)
        for name, pos in zip(names, (hj, knee, ankle, toe), strict=True):
            out[:, _J[name]] = pos


def _place_spine(
    out: np.ndarray, p: _Plan, pelvis: np.ndarray, lean: np.ndarray, twist: np.ndarray
) -> np.ndarray:
    """Write the spine, neck and head, stacked above the pelvis leaning forward by
    ``lean``, into ``out``; return the torso yaw ``yaw - 0.6 twist`` (n,)."""
    tyaw = p.yaw - 0.6 * twist
    up = np.stack([np.zeros(p.n), np.cos(lean), np.sin(lean)], -1)
    seg = {"Spine": 0.157, "Spine1": 0.090, "Neck": 0.164, "Head": 0.065}
    prev = pelvis
    for name, length in seg.items():
        prev = prev + rotate_y(up * length * p.sc, tyaw)
        out[:, _J[name]] = prev
    return tyaw


def _place_arms(
    out: np.ndarray,
    p: _Plan,
    style: dict,
    ankles: list[np.ndarray],
    lean: np.ndarray,
    tyaw: np.ndarray,
) -> None:
    """Write both arms into ``out``: the swing follows the opposite foot (counter-swing),
    the elbow bends more when running."""
    n, sc, run = p.n, p.sc, p.run
    chest = out[:, _J["Spine1"]]
    rel = [rotate_y(a - p.root, -p.yaw)[:, 2] for a in ankles]
    for side, names, own, other in (
        (1.0, _ARMS[0], rel[0], rel[1]),
        (-1.0, _ARMS[1], rel[1], rel[0]),
    ):
        swing = np.clip(style["arm"] * (0.7 + 0.5 * run) * (other - own), -0.9, 0.9)
        swing = gaussian_smooth(swing, 1.0)
        shoulder = chest + rotate_y(
            np.stack([side * 0.10 * sc * np.ones(n), 0.133 * sc * np.ones(n),
                      -0.01 * np.ones(n)], -1), tyaw)  # fmt: skip
        ab = style["abduct"]
        ang1 = swing + 0.3 * lean - 0.15 - 0.3 * run
        d1 = np.stack([side * np.sin(ab) * np.ones(n), -np.cos(ab) * np.cos(ang1),
                       np.cos(ab) * np.sin(ang1)], -1)  # fmt: skip
        bend = style["elbow"] + 1.1 * run + 0.3 * np.maximum(swing, 0)
        ang2 = ang1 + bend
        d2 = np.stack([side * 0.5 * np.sin(ab) * np.ones(n), -np.cos(ang2), np.sin(ang2)], -1)
        d2 /= np.linalg.norm(d2, axis=-1, keepdims=True)
        ang3 = ang2 + 0.15
        d3 = np.stack([side * 0.4 * np.sin(ab) * np.ones(n), -np.cos(ang3), np.sin(ang3)], -1)
        d3 /= np.linalg.norm(d3, axis=-1, keepdims=True)
        elbow = shoulder + rotate_y(d1 * 0.243 * sc, tyaw)
        hand = elbow + rotate_y(d2 * 0.223 * sc, tyaw)
        tip = hand + rotate_y(d3 * 0.08, tyaw)
        for name, pos in zip(names, (shoulder, elbow, hand, tip), strict=True):
            out[:, _J[name]] = pos


def _add_noise(rng: np.random.Generator, out: np.ndarray, style: dict) -> None:
    """Add smooth noise (std ``style["noise"]`` m) to every joint but the feet and toes
    (they stay planted)."""
    n = out.shape[0]
    noisy = [_J[x] for x in JOINT_NAMES if "Foot" not in x and "Toe" not in x]
    noise = gaussian_smooth(rng.normal(0, 1, (n, len(noisy), 3)), 0.15 * SRC_FPS)
    noise *= style["noise"] / max(noise.std(), 1e-9)
    out[:, noisy] += noise


def _simulate(rng: np.random.Generator, n: int, style: dict, planned: np.ndarray):
    """World positions (n, 21, 3) metres of one clip at SRC_FPS."""
    p = _plan(rng, n, style, planned)
    feet = [_foot(p, style, side, offset) for side, offset in ((1.0, 0.0), (-1.0, 0.5))]
    pelvis, hip_nom, lean, twist = _pelvis(rng, p, style)
    out = np.zeros((n, NUM_JOINTS, 3))
    _place_legs(out, p, pelvis, hip_nom, twist, feet)
    tyaw = _place_spine(out, p, pelvis, lean, twist)
    _place_arms(out, p, style, [ankle for ankle, _, _ in feet], lean, tyaw)
    _add_noise(rng, out, style)
    return out


def generate(
    n_clips: int = 120,
    seconds: float = 12.0,
    seed: int = 0,
    *,
    fps: float = DEFAULT_FPS,
    root_sigma_s: float = ROOT_SIGMA_S,
) -> list[Clip]:
    """``n_clips`` random locomotion clips of ``seconds`` each, as features at ``fps`` (root
    smoothed over ``root_sigma_s`` seconds, as real data).

    Deterministic in ``seed``. Each clip's ``meta`` holds its style parameters and
    ``performer`` (one of four synthetic "performers", by clip index) for performer splits.
    """
    if int(n_clips) < 1:
        raise ValueError(f"n_clips must be >= 1, got {n_clips}")
    if not (np.isfinite(seconds) and seconds * min(fps, SRC_FPS) >= 2):
        raise ValueError(f"seconds must give at least 2 frames, got {seconds}")
    clips = []
    for i in range(int(n_clips)):
        rng = np.random.default_rng([int(seed), i, 7])
        n = int(round(seconds * SRC_FPS)) + 1
        style = random_style(rng)
        planned = random_controls(rng, n, SRC_FPS)
        world = _simulate(rng, n, style, planned)
        meta = {"source": "synthetic", "performer": f"S{i % 4}", "content": "mixed",
                "seed": int(seed), "index": i,
                "style": {k: float(v) for k, v in style.items()}}  # fmt: skip
        clips.append(
            features_from_positions(
                world,
                SRC_FPS,
                fps,
                name=f"synthetic_{seed}_{i:04d}",
                meta=meta,
                root_sigma_s=root_sigma_s,
            )
        )
    return clips


def straight_walk(
    speed: float, seconds: float = 6.0, seed: int = 0, *, fps: float = DEFAULT_FPS
) -> Clip:
    """One clip walking (or running) straight ahead at a constant ``speed`` m/s (tests)."""
    rng = np.random.default_rng([int(seed), 99])
    n = int(round(seconds * SRC_FPS)) + 1
    style = random_style(rng)
    planned = np.tile([speed, 0.0, 0.0], (n, 1))
    world = _simulate(rng, n, style, planned)
    return features_from_positions(
        world, SRC_FPS, fps, name=f"straight_{speed:g}", meta={"source": "synthetic"}
    )
