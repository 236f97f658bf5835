"""Skeleton mappings: which joints of a BVH file become the 21 project joints.

A :class:`SkeletonMapping` lists, in ``names.JOINT_NAMES`` order, either the BVH joint
whose world position is used, or a :class:`VirtualJoint`: a rigid point
``p = p_w[parent] + R_w[parent] @ offset`` attached to a BVH joint (used for the Bandai
hand-index joints, which the data do not have: a pseudo-fingertip 8 cm along the hand
bone, ``Hand_X + R_w(Hand_X) @ (+-8 cm, 0, 0)``, + for L and - for R, because Bandai's
arm bones point along +x on the left and -x on the right). Never duplicate a joint's
coordinates: identical channels make the data covariance singular.

Built in: ``"bandai"`` (Bandai-Namco Research Motiondataset, cm, y up) and ``"cmu"``
(the 31-joint CMU cgspeed BVH, 1 unit = 1/0.45 inch, y up; Holden's 21-joint selection).
Add your own with :func:`register_skeleton` (or pass a mapping object / dict directly).
"""

from __future__ import annotations

import dataclasses

import numpy as np

from motionflows.data.bvh import BVH, forward_kinematics
from motionflows.data.names import JOINT_NAMES, NUM_JOINTS
from motionflows.errors import MotionDataError


@dataclasses.dataclass(frozen=True)
class VirtualJoint:
    """A point rigidly attached to BVH joint ``parent`` at ``offset`` (parent's local frame,
    file units)."""

    parent: str
    offset: tuple[float, float, float]


@dataclasses.dataclass(frozen=True)
class SkeletonMapping:
    """How to read the 21 project joints from a BVH skeleton.

    Attributes:
      name: registry name.
      joints: 21 entries in ``JOINT_NAMES`` order: a BVH joint name or a ``VirtualJoint``.
      unit: metres per file unit (Bandai cm: 0.01).
      up: the file's up axis, ``"y"`` or ``"z"`` (z-up data are rotated to y-up).
      description: free text.
    """

    name: str
    joints: tuple[str | VirtualJoint, ...]
    unit: float
    up: str = "y"
    description: str = ""

    def __post_init__(self):
        if len(self.joints) != NUM_JOINTS:
            raise ValueError(
                f"skeleton {self.name!r} maps {len(self.joints)} joints; it must list "
                f"{NUM_JOINTS} in the order {JOINT_NAMES}"
            )
        if not (np.isfinite(self.unit) and self.unit > 0):
            raise ValueError(f"skeleton {self.name!r}: unit must be > 0 (metres per unit)")
        if self.up not in ("y", "z"):
            raise ValueError(f"skeleton {self.name!r}: up must be 'y' or 'z', got {self.up!r}")
        real = [j for j in self.joints if isinstance(j, str)]
        if len(set(real)) != len(real):
            raise ValueError(
                f"skeleton {self.name!r} uses a BVH joint twice; duplicated coordinates make "
                "the data covariance singular (use a VirtualJoint instead)"
            )

    def to_dict(self) -> dict:
        joints = [
            j if isinstance(j, str) else {"parent": j.parent, "offset": list(j.offset)}
            for j in self.joints
        ]
        return {
            "name": self.name,
            "joints": joints,
            "unit": self.unit,
            "up": self.up,
            "description": self.description,
        }

    @classmethod
    def from_dict(cls, d: dict) -> SkeletonMapping:
        joints = tuple(
            j if isinstance(j, str) else VirtualJoint(j["parent"], tuple(j["offset"]))
            for j in d["joints"]
        )
        return cls(d["name"], joints, float(d["unit"]), d.get("up", "y"), d.get("description", ""))


BANDAI = SkeletonMapping(
    name="bandai",
    joints=(
        "Hips",
        "UpperLeg_L",
        "LowerLeg_L",
        "Foot_L",
        "Toes_L",
        "UpperLeg_R",
        "LowerLeg_R",
        "Foot_R",
        "Toes_R",
        "Spine",
        "Chest",
        "Neck",
        "Head",
        "UpperArm_L",
        "LowerArm_L",
        "Hand_L",
        VirtualJoint("Hand_L", (8.0, 0.0, 0.0)),
        "UpperArm_R",
        "LowerArm_R",
        "Hand_R",
        VirtualJoint("Hand_R", (-8.0, 0.0, 0.0)),
    ),  # fmt: skip
    unit=0.01,
    description="Bandai-Namco-Research-Motiondataset (cm, y up); hand index = rigid "
    "pseudo-fingertip 8 cm along the hand bone",
)

CMU = SkeletonMapping(
    name="cmu",
    joints=(
        "Hips",
        "LeftUpLeg",
        "LeftLeg",
        "LeftFoot",
        "LeftToeBase",
        "RightUpLeg",
        "RightLeg",
        "RightFoot",
        "RightToeBase",
        "Spine",
        "Spine1",
        "Neck1",
        "Head",
        "LeftArm",
        "LeftForeArm",
        "LeftHand",
        "LeftHandIndex1",
        "RightArm",
        "RightForeArm",
        "RightHand",
        "RightHandIndex1",
    ),  # fmt: skip
    unit=0.0254 / 0.45,
    description="CMU mocap, 31-joint cgspeed BVH (1 unit = 1/0.45 inch, y up); Holden's "
    "21-joint selection",
)

_REGISTRY: dict[str, SkeletonMapping] = {"bandai": BANDAI, "cmu": CMU}


def register_skeleton(mapping: SkeletonMapping | dict, *, overwrite: bool = False) -> None:
    """Make ``mapping`` available by name to ``clip_from_bvh`` / ``load_dataset``."""
    if isinstance(mapping, dict):
        mapping = SkeletonMapping.from_dict(mapping)
    if mapping.name in _REGISTRY and not overwrite:
        raise ValueError(f"skeleton {mapping.name!r} exists; pass overwrite=True to replace it")
    _REGISTRY[mapping.name] = mapping


def skeleton_names() -> tuple[str, ...]:
    return tuple(sorted(_REGISTRY))


def get_skeleton(skeleton: str | SkeletonMapping | dict) -> SkeletonMapping:
    """Look up a mapping by name (or pass a mapping / dict through)."""
    if isinstance(skeleton, SkeletonMapping):
        return skeleton
    if isinstance(skeleton, dict):
        return SkeletonMapping.from_dict(skeleton)
    if skeleton not in _REGISTRY:
        raise ValueError(
            f"unknown skeleton {skeleton!r}; known: {', '.join(skeleton_names())} "
            "(add one with motionflows.data.skeleton.register_skeleton)"
        )
    return _REGISTRY[skeleton]


def joint_positions(bvh: BVH, skeleton: str | SkeletonMapping | dict = "bandai") -> np.ndarray:
    """World positions (F, 21, 3) in metres, y up, of the 21 project joints."""
    mapping = get_skeleton(skeleton)
    missing = sorted(
        {j if isinstance(j, str) else j.parent for j in mapping.joints} - set(bvh.names)
    )
    if missing:
        raise MotionDataError(
            f"skeleton mapping {mapping.name!r} needs joint(s) {missing} that the file does "
            f"not have (its joints: {', '.join(bvh.names)}); choose another skeleton= or "
            "register a mapping for this file",
            path=bvh.path,
        )
    world_p, world_r = forward_kinematics(bvh, return_rotations=True)
    out = np.empty((bvh.num_frames, NUM_JOINTS, 3), dtype=np.float64)
    for k, joint in enumerate(mapping.joints):
        if isinstance(joint, str):
            out[:, k] = world_p[:, bvh.names.index(joint)]
        else:
            j = bvh.names.index(joint.parent)
            out[:, k] = world_p[:, j] + world_r[:, j] @ np.asarray(joint.offset, np.float64)
    out *= mapping.unit
    if mapping.up == "z":
        out = np.stack([out[..., 0], out[..., 2], -out[..., 1]], axis=-1)
    return out
