"""Motion data: BVH -> 21-joint features (63 pose + 3 control), datasets and batches.

Two lines to data::

    from motionflows.data import load_dataset
    ds = load_dataset("synthetic")      # or "bandai" (local folder), or "bvh" (path=...)

Feature layout and units: :mod:`motionflows.data.names`. Pipeline: :mod:`.bvh` (parser and
forward kinematics), :mod:`.skeleton` (joint mappings), :mod:`.features` (the recipe),
:mod:`.synthetic` (procedural locomotion), :mod:`.augment`, :mod:`.pipeline` (windows,
standardiser, batch indices), :mod:`.datasets` (sources, splits, cache), :mod:`.controls`
(control presets), :mod:`.download` (the Bandai files).
"""

from motionflows.data.augment import mirror_clip, reverse_clip
from motionflows.data.bvh import BVH, forward_kinematics, parse_bvh, read_bvh
from motionflows.data.controls import load_control
from motionflows.data.datasets import MotionDataset, load_dataset
from motionflows.data.features import (
    Clip,
    clip_from_bvh,
    features_from_positions,
    integrate_control,
    world_from_features,
)
from motionflows.data.pipeline import Standardizer, WindowSet
from motionflows.data.skeleton import SkeletonMapping, VirtualJoint, register_skeleton
from motionflows.data.sources import SOURCES, load_clips
from motionflows.errors import MotionDataError

__all__ = [
    "BVH",
    "Clip",
    "MotionDataError",
    "MotionDataset",
    "SOURCES",
    "SkeletonMapping",
    "Standardizer",
    "VirtualJoint",
    "WindowSet",
    "clip_from_bvh",
    "features_from_positions",
    "forward_kinematics",
    "integrate_control",
    "load_clips",
    "load_control",
    "load_dataset",
    "mirror_clip",
    "parse_bvh",
    "read_bvh",
    "register_skeleton",
    "reverse_clip",
    "world_from_features",
]
