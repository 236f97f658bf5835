"""One streamed character: a causal model stepped frame by frame, placed on its root path.

Units. The page speaks in seconds: a target control is ``(forward m/s, sideways m/s,
turn rad/s)`` (sideways + = left, turn + = counter-clockwise seen from above, as in
``motionflows.data.names``). The model speaks per frame: control ``c_t`` in m/frame and
rad/frame, standardised with the run's standardiser before ``stream_step``, and the pose it
returns is de-standardised to metres in the root frame (the same conversions as
``motionflows.training.draw_samples``).

Per frame t (fps f, period dt = 1/f)::

    applied  <- applied + (target - applied) * (1 - exp(-dt / RAMP_SECONDS))   (m/s, rad/s)
    c_t       = applied / f                                                     (data units)
    pose_t    = destandardise(stream_step(state, standardise(c_t)))             (63, metres)
    world_t   = p_t + R_y(yaw_t) pose_t,   then (p, yaw) advance by c_t

with ``R_y`` and the advance of ``motionflows.evaluation.motion.integrate_root``, so the
recorded (pose, control) placed by ``to_global`` gives back the streamed world joints.
"""

from __future__ import annotations

import math
import threading
from collections import deque
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
from flax import nnx

from motionflows.data.names import NUM_JOINTS, POSE_DIM
from motionflows.foot_lock import StreamingFootLock, _to_root_frame
from motionflows.inference import stream_stepper, streaming_model

RAMP_SECONDS = 0.25
"""Time constant of the control ramp: 63 % of a change is applied after this many seconds."""

MAX_RECORD_FRAMES = 20 * 60 * 20
"""The recording keeps the last 20 minutes at 20 fps (about 6 MB of poses)."""


def ramp(applied: np.ndarray, target: np.ndarray, dt: float, seconds: float = RAMP_SECONDS):
    """First-order approach of ``applied`` to ``target`` over one frame of ``dt`` seconds."""
    alpha = 1.0 - math.exp(-dt / seconds) if seconds > 0 else 1.0
    return applied + (target - applied) * alpha


def place(pose: np.ndarray, position: np.ndarray, yaw: float) -> np.ndarray:
    """Root-frame joints (63,) -> world joints (21, 3): ``position + R_y(yaw) joint``.

    ``R_y`` as in ``motionflows.evaluation.motion.integrate_root``: local +z (facing) ->
    (sin yaw, 0, cos yaw), local +x (left) -> (cos yaw, 0, -sin yaw); heights unchanged.
    """
    j = np.asarray(pose, np.float64).reshape(NUM_JOINTS, 3)
    cos, sin = math.cos(yaw), math.sin(yaw)
    x = position[0] + j[:, 0] * cos + j[:, 2] * sin
    z = position[2] - j[:, 0] * sin + j[:, 2] * cos
    return np.stack([x, j[:, 1], z], axis=-1)


def advance(position: np.ndarray, yaw: float, control: np.ndarray) -> tuple[np.ndarray, float]:
    """One step of ``integrate_root``: control (3,) m/frame, rad/frame -> next (p, yaw)."""
    fwd, side, turn = (float(v) for v in control)
    cos, sin = math.cos(yaw), math.sin(yaw)
    step = np.array([side * cos + fwd * sin, 0.0, -side * sin + fwd * cos])
    return position + step, yaw + turn


class Character:
    """A model, its standardiser and the live state of one character.

    Not thread-safe except :meth:`recording`: one thread (the engine) calls
    :meth:`step`, :meth:`reset` and sets :attr:`target` / :attr:`temperature`.

    Args:
      model: a causal model with ``init_stream(batch)`` and
        ``stream_step(state, control_t, key, temperature=...)`` (standardised units); a
        Flax module is streamed as :func:`~motionflows.inference.streaming_model` says.
      standardizer: the run's standardiser (``normalize_control``, ``denormalize_pose``).
      fps: frames per second of the run's data.
      temperature: latent temperature (1 samples the model, 0 its mode path).
      seed: seed of the latent draws; each reset folds in a new episode number.
      foot_lock: hold planted feet (:class:`~motionflows.foot_lock.StreamingFootLock`, a
        post-process of each frame; the recording then keeps the drawn poses as
        ``pose_drawn`` beside the shown ones).
    """

    def __init__(
        self,
        model: Any,
        standardizer: Any,
        fps: float,
        *,
        temperature: float = 1.0,
        seed=0,
        foot_lock: bool = False,
    ):
        if not (hasattr(model, "init_stream") and hasattr(model, "stream_step")):
            raise ValueError(
                f"{type(model).__name__} has no streaming step (init_stream / stream_step); "
                "play needs a causal frame-by-frame model such as MoGlow"
            )
        if isinstance(model, nnx.Module):  # separate step weights: the same poses, faster
            model = streaming_model(model)
        self.model, self.standardizer, self.fps = model, standardizer, float(fps)
        self.temperature = float(temperature)
        self._step = stream_stepper(model)
        self._base_key = jax.random.key(seed)
        self.foot_lock = StreamingFootLock(fps=self.fps) if foot_lock else None
        self._lock = threading.Lock()
        self.episode = -1
        self.reset()

    def reset(self, *, keep_recording: bool = False) -> None:
        """Back to standing at the origin facing +z: fresh model state, zero control,
        a new latent key and an empty recording, or with ``keep_recording`` (the engine's
        reset after a diverged frame) the recording so far, the restart marked in its
        ``resets``."""
        self.episode += 1
        self.state = self.model.init_stream(1)
        self.key = jax.random.fold_in(self._base_key, self.episode)
        self.target = np.zeros(3)  # m/s, m/s, rad/s
        self.applied = np.zeros(3)
        self.position, self.yaw = np.zeros(3), 0.0
        self.t = 0
        if self.foot_lock is not None:
            self.foot_lock.reset()
        with self._lock:
            if keep_recording:
                self._resets.append(self._recorded)
                return
            self._poses: deque = deque(maxlen=MAX_RECORD_FRAMES)
            self._drawn: deque = deque(maxlen=MAX_RECORD_FRAMES)
            self._controls: deque = deque(maxlen=MAX_RECORD_FRAMES)
            self._recorded = 0  # frames appended since the recording began
            self._resets: list[int] = []  # values of _recorded at each kept restart

    def warm_up(self) -> None:
        """Compile the step (a throwaway frame), so the first page gets frames at once."""
        pose, _ = self._step(self.state, jnp.zeros((1, 3)), self.key, jnp.float32(0.0))
        jax.block_until_ready(pose)

    def step(self) -> dict:
        """Generate frame t, place it, advance the root; returns the frame's fields.

        ``joints`` (21, 3) world metres; ``pose`` (63,) root-frame metres (both with the
        planted feet held under ``foot_lock``, which adds ``pose_drawn``); ``control``
        (3,) m/frame, rad/frame (the one moving frame t to t + 1); ``position`` (3,) and
        ``yaw`` the root of frame t; ``applied`` (3,) m/s, m/s, rad/s.
        """
        dt = 1.0 / self.fps
        self.applied = ramp(self.applied, self.target, dt)
        control = (self.applied * dt).astype(np.float32)
        c_std = np.asarray(self.standardizer.normalize_control(control[None]), np.float32)
        pose_std, self.state = self._step(
            self.state, c_std, self.key, jnp.float32(self.temperature)
        )
        pose = np.asarray(self.standardizer.denormalize_pose(np.asarray(pose_std)[0]))
        pose = pose.astype(np.float32)
        if not np.all(np.isfinite(pose)):
            # a diverged frame is never drawn; the next reset starts clean
            raise FloatingPointError("the model produced a non-finite pose")
        joints, drawn = place(pose, self.position, self.yaw), pose
        if self.foot_lock is not None:
            held = self.foot_lock.step(joints, self.yaw)
            pose = drawn + _to_root_frame(held - joints, np.float64(self.yaw)).reshape(-1)
            joints, pose = held, pose.astype(np.float32)
        frame = {
            "t": self.t,
            "joints": joints,
            "pose": pose,
            "control": control,
            "position": self.position.copy(),
            "yaw": self.yaw,
            "applied": self.applied.copy(),
        }
        if self.foot_lock is not None:
            frame["pose_drawn"] = drawn
        with self._lock:
            self._poses.append(pose)
            if self.foot_lock is not None:
                self._drawn.append(drawn)
            self._controls.append(control)
            self._recorded += 1
        self.position, self.yaw = advance(self.position, self.yaw, control)
        self.t += 1
        return frame

    def recording(self) -> dict[str, np.ndarray]:
        """The frames since the last reset, at most the last :data:`MAX_RECORD_FRAMES`:
        ``pose`` (T, 63) root-frame metres and ``control`` (T, 3) m/frame, rad/frame (what
        ``motionflows render`` reads), ``fps``, ``resets`` (R,) the frames at which the
        character restarted standing after a diverged frame (the recording keeps the motion
        before it); under ``foot_lock`` ``pose`` is the shown (locked) one and
        ``pose_drawn`` the model's."""
        with self._lock:
            pose = np.asarray(self._poses, np.float32).reshape(-1, POSE_DIM)
            drawn = np.asarray(self._drawn, np.float32).reshape(-1, POSE_DIM)
            control = np.asarray(self._controls, np.float32).reshape(-1, 3)
            dropped = self._recorded - len(self._poses)  # the oldest, beyond the limit
            resets = np.array([r - dropped for r in self._resets if r > dropped], np.int64)
        out = {"pose": pose, "control": control, "fps": np.float32(self.fps), "resets": resets}
        if self.foot_lock is not None:
            out["pose_drawn"] = drawn
        return out
