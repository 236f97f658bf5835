"""The one place where the motion feature layout is named.

Pose: 21 joints x (x, y, z) positions in metres in the floor-projected root frame
(y up, the character faces +z, +x is the character's left), flattened joint-major:
``pose[..., 3 * j + k]`` is coordinate k of joint ``JOINT_NAMES[j]``.

Control, per frame t: the root displacement from frame t to t + 1 expressed in the root
frame of t: ``forward`` (m), ``sideways`` (m, + = left) and ``turn`` (rad, + = counter-
clockwise seen from above, i.e. a left turn).
"""

from __future__ import annotations

JOINT_NAMES: tuple[str, ...] = (
    "Hips",
    "LeftUpLeg", "LeftLeg", "LeftFoot", "LeftToe",
    "RightUpLeg", "RightLeg", "RightFoot", "RightToe",
    "Spine", "Spine1", "Neck", "Head",
    "LeftArm", "LeftForeArm", "LeftHand", "LeftHandIndex",
    "RightArm", "RightForeArm", "RightHand", "RightHandIndex",
)  # fmt: skip
"""Joint order of the 21-joint Holden / MoGlow / Edinburgh skeleton."""

PARENTS: tuple[int, ...] = (
    -1, 0, 1, 2, 3, 0, 5, 6, 7, 0, 9, 10, 11, 11, 13, 14, 15, 11, 17, 18, 19,
)  # fmt: skip
"""Parent index of each joint (for drawing bones and measuring bone lengths)."""

MIRROR_JOINTS: tuple[int, ...] = (
    0, 5, 6, 7, 8, 1, 2, 3, 4, 9, 10, 11, 12, 17, 18, 19, 20, 13, 14, 15, 16,
)  # fmt: skip
"""Joint permutation that swaps left and right (an involution)."""

FOOT_JOINTS: tuple[int, ...] = (3, 4, 7, 8)
"""Left ankle, left toe, right ankle, right toe."""

NUM_JOINTS = len(JOINT_NAMES)
POSE_DIM = 3 * NUM_JOINTS  # 63
CONTROL_NAMES: tuple[str, ...] = ("forward", "sideways", "turn")
CONTROL_UNITS: tuple[str, ...] = ("m/frame", "m/frame", "rad/frame")
CONTROL_DIM = len(CONTROL_NAMES)  # 3
DEFAULT_FPS = 20.0
DEFAULT_WINDOW = 80  # 4 s at 20 fps
