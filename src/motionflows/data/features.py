"""World joint positions -> the project's 63 pose + 3 control features (one code path).

Recipe (FEATURES.md, Holden et al. 2016 with the two documented fixes), for world positions
``P[t, 21, 3]`` in metres, y up:

1. Resample to the target rate by linear interpolation at ``t = k / fps``.
2. Floor: subtract the plain minimum over the clip of the ankle and toe heights.
3. Root: ``ref[t] = Hips[t] * (1, 0, 1)``, Gaussian-smoothed over time (sigma 1/3 s, the
   facing's; Holden used 0.05 s). The longer smoothing keeps the gait cycle out of the
   control: the hip's sway and its speed changes within a stride stay in the pose, and the
   control says only where the character travels, as a user's control (a game pad, a
   preset path) does. With 0.05 s the control oscillates with the stride, and a motion whose
   stride phase differs from the control's slides its planted feet by the oscillation
   (real poses on their own control shifted by 5 frames slide at 0.35 m/s, 5.5x their 0.065
   m/s; with 1/3 s, 0.10 m/s; docs/readme/moglow_quality.md).
4. Facing: ``across = (LeftArm - RightArm) + (LeftUpLeg - RightUpLeg)`` (floor-projected,
   normalised), ``forward = across x (0, 1, 0)``, ``yaw[t] = atan2(forward.x, forward.z)``
   (+ = counter-clockwise seen from above), unwrapped and Gaussian-smoothed (sigma 1/3 s).
   Smoothing uses odd reflection at the clip ends, so constant velocities and turning
   rates are not biased towards zero near the ends.
5. Pose: ``R_y(-yaw[t]) @ (P[t, j] - ref[t])`` for x, z; y stays the height above the
   floor. The character faces +z and +x is its left.
6. Control for t = 0 .. T-2 (DESIGN.md order and signs):
   ``(sideways, forward) = (R_y(-yaw[t]) @ (ref[t+1] - ref[t]))_{x, z}`` (metres/frame,
   in the root frame of t) and ``turn = wrap(yaw[t+1] - yaw[t])`` (rad/frame, + = left).
   The clip keeps frames 0 .. T-2 (the last frame only supplies the final control), so
   ``pose`` and ``control`` are both (T-1, .).

With ``R_y(a) = [[cos a, 0, sin a], [0, 1, 0], [-sin a, 0, cos a]]`` the control integrates
back exactly: ``ref[t+1] = ref[t] + R_y(yaw[t]) @ (sideways, 0, forward)``,
``yaw[t+1] = yaw[t] + turn`` (:func:`integrate_control`).
"""

from __future__ import annotations

import dataclasses
import os
from pathlib import Path
from typing import Any

import numpy as np

from motionflows.data.names import (
    CONTROL_DIM,
    DEFAULT_FPS,
    FOOT_JOINTS,
    JOINT_NAMES,
    NUM_JOINTS,
    POSE_DIM,
)
from motionflows.errors import MotionDataError

ROOT_SIGMA_S = 1.0 / 3.0
"""Root smoothing (seconds): the facing's timescale, long enough to remove the gait cycle
from the control (module docstring, step 3). Holden et al. used 0.05 s (3 frames at 60 fps)."""
HOLDEN_ROOT_SIGMA_S = 0.05
"""Holden et al.'s root smoothing (3 frames at 60 fps): the features of the MoGlow and VAE-LSTM
papers' data, of the ``paper`` presets, and of every run saved before ``data.root_sigma_s``
existed (2026-12-02)."""
MAX_POSITION_M = 1000.0
"""Largest accepted |joint coordinate| in metres after unit conversion (1 km)."""
MAX_RESAMPLED_FRAMES = 360_000
"""Longest accepted clip after resampling: 5 hours at 20 fps (~180 MB per position array)."""
MAX_UPSAMPLE = 200.0
"""Largest accepted ratio of target to source frame rate: resampling never makes a clip
more than 200 times longer (in frames) than the file it was read from."""
FACING_SIGMA_S = 1.0 / 3.0  # 20 frames at 60 fps
_HIP = JOINT_NAMES.index("Hips")
_LARM, _RARM = JOINT_NAMES.index("LeftArm"), JOINT_NAMES.index("RightArm")
_LUL, _RUL = JOINT_NAMES.index("LeftUpLeg"), JOINT_NAMES.index("RightUpLeg")


@dataclasses.dataclass
class Clip:
    """One take as features.

    Attributes:
      pose: (T, 63) float32, joint positions in metres in the floor-projected root frame.
      control: (T, 3) float32, (forward m/frame, sideways m/frame + left, turn rad/frame +
        counter-clockwise) moving frame t to t + 1, in the root frame of t.
      fps: frames per second.
      name: take name (unique within a dataset; splits are by take).
      meta: free-form metadata (source file, content, style, performer, ...).
    """

    pose: np.ndarray
    control: np.ndarray
    fps: float = DEFAULT_FPS
    name: str = "clip"
    meta: dict = dataclasses.field(default_factory=dict)

    def __post_init__(self):
        self.pose = np.asarray(self.pose, dtype=np.float32)
        self.control = np.asarray(self.control, dtype=np.float32)
        if self.pose.ndim != 2 or self.pose.shape[1] != POSE_DIM:
            raise ValueError(f"Clip.pose must be (T, {POSE_DIM}), got {self.pose.shape}")
        if self.control.shape != (self.pose.shape[0], CONTROL_DIM):
            raise ValueError(
                f"Clip.control must be (T, {CONTROL_DIM}) with T = {self.pose.shape[0]}, "
                f"got {self.control.shape}"
            )

    def __len__(self) -> int:
        return int(self.pose.shape[0])

    @property
    def seconds(self) -> float:
        return len(self) / self.fps


def gaussian_smooth(x: np.ndarray, sigma: float, axis: int = 0) -> np.ndarray:
    """Gaussian filter along ``axis``; sigma in samples.

    Edges use odd (point) reflection, ``x[-k] = 2 x[0] - x[k]``, so a linear trend (constant
    velocity or turning rate) passes unchanged up to the ends of the clip.
    """
    x = np.asarray(x, dtype=np.float64)
    if sigma <= 0 or x.shape[axis] < 2:
        return x.copy()
    radius = int(np.ceil(4.0 * sigma))
    taps = np.arange(-radius, radius + 1)
    kernel = np.exp(-0.5 * (taps / sigma) ** 2)
    kernel /= kernel.sum()
    x = np.moveaxis(x, axis, 0)
    n = x.shape[0]
    k = np.minimum(np.arange(1, radius + 1), n - 1)
    left = 2.0 * x[:1] - x[k[::-1]]
    right = 2.0 * x[-1:] - x[(n - 1 - k)]
    padded = np.concatenate([left, x, right], axis=0)
    out = np.zeros_like(x)
    for i, w in enumerate(kernel):
        out += w * padded[i : i + n]
    return np.moveaxis(out, 0, axis)


def resample(x: np.ndarray, src_fps: float, dst_fps: float) -> np.ndarray:
    """Linearly interpolate frames (axis 0) sampled at ``src_fps`` at ``t = k / dst_fps``.

    Keeps every target time within the source span: ``K = floor((F-1) dst/src) + 1``.
    Raises ``ValueError`` before allocating anything if ``dst/src > MAX_UPSAMPLE`` or
    ``K > MAX_RESAMPLED_FRAMES``.
    """
    x = np.asarray(x, dtype=np.float64)
    if abs(src_fps - dst_fps) < 1e-5 * dst_fps:  # a BVH's Frame Time has ~6 digits
        return x.copy()
    n = x.shape[0]
    ratio = dst_fps / src_fps
    if not ratio <= MAX_UPSAMPLE:
        raise ValueError(
            f"resampling {src_fps:g} fps to {dst_fps:g} fps would make the clip {ratio:g} "
            f"times longer, beyond the limit of {MAX_UPSAMPLE:g}; check the source frame "
            "rate (BVH Frame Time) or choose a lower target fps"
        )
    count = int(np.floor((n - 1) * ratio + 1e-6)) + 1
    if count > MAX_RESAMPLED_FRAMES:
        raise ValueError(
            f"resampling {n} frames at {src_fps:g} fps to {dst_fps:g} fps gives {count} "
            f"frames, beyond the limit of {MAX_RESAMPLED_FRAMES} "
            f"({MAX_RESAMPLED_FRAMES / dst_fps:g} s); split the take into shorter files"
        )
    t = np.arange(count) * (src_fps / dst_fps)
    i0 = np.minimum(np.floor(t).astype(np.int64), n - 1)
    i1 = np.minimum(i0 + 1, n - 1)
    w = (t - i0).reshape((-1,) + (1,) * (x.ndim - 1))
    return (1.0 - w) * x[i0] + w * x[i1]


def rotate_y(v: np.ndarray, angle: np.ndarray) -> np.ndarray:
    """Apply ``R_y(angle)`` to the (x, z) of ``v`` (..., 3) (angle broadcast over ...)."""
    c, s = np.cos(angle), np.sin(angle)
    x, y, z = np.broadcast_arrays(v[..., 0], v[..., 1], v[..., 2], c)[:3]
    return np.stack([c * x + s * z, y + 0 * c, -s * x + c * z], axis=-1)


def wrap_angle(a: np.ndarray) -> np.ndarray:
    """Wrap to (-pi, pi]."""
    return np.pi - np.mod(np.pi - a, 2.0 * np.pi)


def facing_yaw(world: np.ndarray, fps: float, sigma_s: float = FACING_SIGMA_S) -> np.ndarray:
    """(T,) unwrapped heading from shoulder and hip across-vectors, smoothed."""
    across = (world[:, _LARM] - world[:, _RARM]) + (world[:, _LUL] - world[:, _RUL])
    across[:, 1] = 0.0
    norm = np.linalg.norm(across, axis=-1, keepdims=True)
    forward = np.stack([-across[:, 2], np.zeros(len(across)), across[:, 0]], axis=-1)
    forward = forward / np.maximum(norm, 1e-9)
    yaw = np.unwrap(np.arctan2(forward[:, 0], forward[:, 2]))
    return gaussian_smooth(yaw, sigma_s * fps)


def features_from_positions(
    world: np.ndarray,
    src_fps: float,
    fps: float = DEFAULT_FPS,
    *,
    name: str = "clip",
    meta: dict | None = None,
    path: str | None = None,
    root_sigma_s: float = ROOT_SIGMA_S,
) -> Clip:
    """World positions (F, 21, 3) metres y-up at ``src_fps`` -> :class:`Clip` at ``fps``.

    ``root_sigma_s`` is the root's smoothing in seconds (step 3; 0.05 gives Holden's
    features, whose control carries the gait cycle)."""
    world = np.asarray(world, dtype=np.float64)
    if world.ndim != 3 or world.shape[1:] != (NUM_JOINTS, 3):
        raise ValueError(f"world positions must be (F, {NUM_JOINTS}, 3), got {world.shape}")
    bad = ~np.isfinite(world) | (np.abs(np.nan_to_num(world, nan=0.0)) > MAX_POSITION_M)
    if bad.any():
        k, j, _ = (int(v[0]) for v in np.nonzero(bad))
        value = world[k, j][bad[k, j]][0]
        what = "is not finite" if not np.isfinite(value) else f"is {value:g} m"
        raise MotionDataError(
            f"joint {JOINT_NAMES[j]} in frame {k} {what} after conversion to metres, beyond "
            f"the limit of {MAX_POSITION_M:g} m; the file is damaged, or its units or the "
            "skeleton mapping's unit are wrong",
            path=path,
        )
    if not (np.isfinite(fps) and fps > 0 and np.isfinite(src_fps) and src_fps > 0):
        raise ValueError(f"fps must be positive, got fps={fps}, src_fps={src_fps}")
    try:
        p = resample(world, src_fps, fps)
    except ValueError as err:
        raise MotionDataError(str(err), path=path) from None
    if p.shape[0] < 2:
        raise MotionDataError(
            f"the motion is too short: {world.shape[0]} frame(s) at {src_fps:g} fps give "
            f"{p.shape[0]} at {fps:g} fps; at least 2 are needed",
            path=path,
        )
    floor = float(p[:, list(FOOT_JOINTS), 1].min())
    p[..., 1] -= floor
    ref = p[:, _HIP].copy()
    ref[:, 1] = 0.0
    ref = gaussian_smooth(ref, float(root_sigma_s) * fps)
    yaw = facing_yaw(p, fps)
    local = rotate_y(p - ref[:, None, :] * np.array([1.0, 0.0, 1.0]), -yaw[:, None])
    step = rotate_y(ref[1:] - ref[:-1], -yaw[:-1])
    turn = wrap_angle(yaw[1:] - yaw[:-1])
    control = np.stack([step[:, 2], step[:, 0], turn], axis=-1)
    info = dict(meta or {})
    info.update(
        src_fps=float(src_fps),
        floor_m=floor,
        hip_height_m=float(np.mean(p[:, _HIP, 1])),
    )
    return Clip(
        pose=local[:-1].reshape(-1, POSE_DIM),
        control=control,
        fps=float(fps),
        name=name,
        meta=info,
    )


def array_module(a: Any):
    """numpy for numpy input, jax.numpy for jax arrays (so integrate_root works in both)."""
    if type(a).__module__.startswith("jax") or hasattr(a, "aval"):
        import jax.numpy as jnp

        return jnp
    return np


def integrate_root(control: Any) -> tuple[Any, Any]:
    """Chain per-frame root displacements into a world trajectory.

    control (..., T, 3) -> positions (..., T, 3) (y = 0) and yaw (..., T), with
    ``p_0 = 0``, ``yaw_0 = 0`` and, for t < T - 1::

        yaw_{t+1} = yaw_t + turn_t
        p_{t+1}   = p_t + R_y(yaw_t) (sideways_t, 0, forward_t)

    where ``R_y(a)`` rotates counter-clockwise seen from above (+y): local +z (facing) ->
    (sin a, 0, cos a), local +x (left) -> (cos a, 0, -sin a). The last frame's control
    (moving T-1 -> T) is not used.
    """
    shape = tuple(np.shape(control))
    if len(shape) < 2 or shape[-1] != 3:
        raise ValueError(
            f"control must have shape (..., T, 3) = (forward, sideways, turn), got {shape}"
        )
    xp = array_module(control)
    fwd, side, turn = control[..., 0], control[..., 1], control[..., 2]
    zero = xp.zeros_like(turn[..., :1])
    yaw = xp.concatenate([zero, xp.cumsum(turn[..., :-1], axis=-1)], axis=-1)
    cos, sin = xp.cos(yaw), xp.sin(yaw)
    dx = side * cos + fwd * sin
    dz = -side * sin + fwd * cos
    x = xp.concatenate([zero, xp.cumsum(dx[..., :-1], axis=-1)], axis=-1)
    z = xp.concatenate([zero, xp.cumsum(dz[..., :-1], axis=-1)], axis=-1)
    return xp.stack([x, xp.zeros_like(x), z], axis=-1), yaw


def carry_to_next_root(pose: Any, control: Any) -> Any:
    """Root-frame poses of frame t-1 as they would read in frame t's root frame if every
    joint stayed where it is in the world (a planted foot does).

    pose (..., 63) at frame t-1 and control (..., 3) = c_{t-1} (the move t-1 -> t, see
    :func:`integrate_root`) -> (..., 63). Per joint, with d = (sideways, 0, forward)::

        l' = R_y(-turn) (l - d)

    so that ``to_global`` of l' at frame t equals ``to_global`` of l at frame t-1. Works on
    numpy and jax arrays (traced too).
    """
    xp = array_module(pose)
    j = pose.reshape(pose.shape[:-1] + (NUM_JOINTS, 3))
    forward, sideways, turn = control[..., 0:1], control[..., 1:2], control[..., 2:3]
    x, z = j[..., 0] - sideways, j[..., 2] - forward
    cos, sin = xp.cos(turn), xp.sin(turn)
    moved = xp.stack([x * cos - z * sin, j[..., 1], x * sin + z * cos], axis=-1)
    return moved.reshape(pose.shape)


def integrate_control(
    control: np.ndarray, *, yaw0: float = 0.0, start: np.ndarray | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """Root trajectory from a control sequence (inverse of step 6), one frame longer than
    the control: :func:`integrate_root` of ``control`` with one more (unused) frame,
    turned by ``yaw0`` and moved to ``start``.

    Args:
      control: (T, 3) (forward, sideways, turn) per frame.
    Returns:
      positions (T + 1, 3) on the floor (y = 0) and yaw (T + 1,), starting at ``start``
      (default origin) and ``yaw0``.
    """
    control = np.asarray(control, dtype=np.float64)
    pos, yaw = integrate_root(np.concatenate([control, np.zeros((1, 3))], axis=0))
    pos = rotate_y(pos, np.float64(yaw0))
    if start is not None:
        pos = pos + np.asarray(start, dtype=np.float64)
    return pos, yaw + yaw0


def world_from_features(pose: np.ndarray, control: np.ndarray) -> np.ndarray:
    """Rebuild world joint positions (T, 21, 3) from pose (T, 63) and control (T, 3)."""
    pose = np.asarray(pose, dtype=np.float64).reshape(-1, NUM_JOINTS, 3)
    pos, yaw = integrate_control(control)
    n = pose.shape[0]
    return rotate_y(pose, yaw[:n, None]) + pos[:n, None, :]


def clip_from_bvh(
    path: str | os.PathLike,
    fps: float = DEFAULT_FPS,
    skeleton="bandai",
    *,
    name: str | None = None,
    meta: dict | None = None,
    root_sigma_s: float = ROOT_SIGMA_S,
) -> Clip:
    """Read a BVH file and return its features as a :class:`Clip` (see module docstring).

    Args:
      path: the .bvh file.
      fps: target frame rate (20 by default; e.g. 60 for the VAE-LSTM paper preset).
      skeleton: mapping name (``"bandai"``, ``"cmu"``, or registered), or a mapping.
      root_sigma_s: the root's smoothing in seconds (default :data:`ROOT_SIGMA_S`).
    Raises:
      MotionDataError: unreadable or malformed file (names file, line and problem), or a
        skeleton mapping that does not fit the file.
    """
    from motionflows.data.bvh import read_bvh
    from motionflows.data.skeleton import get_skeleton, joint_positions

    mapping = get_skeleton(skeleton)
    bvh = read_bvh(path)
    world = joint_positions(bvh, mapping)
    p = Path(path)
    info = {"file": str(p), "skeleton": mapping.name, "src_frames": bvh.num_frames}
    info.update(meta or {})
    return features_from_positions(
        world, bvh.fps, fps, name=name or p.stem, meta=info, path=str(p), root_sigma_s=root_sigma_s
    )
