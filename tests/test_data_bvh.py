"""BVH parser and forward kinematics on small hand-written files."""

from __future__ import annotations

import numpy as np
import pytest

from motionflows.data.bvh import forward_kinematics, parse_bvh, read_bvh
from motionflows.errors import MotionDataError

# Root with 6 channels in Xpos Ypos Zpos Zrot Xrot Yrot order, a 3-channel child with
# Yrot Xrot Zrot order, and End Sites.
SIMPLE = """HIERARCHY
ROOT Hips
{
  OFFSET 0 0 0
  CHANNELS 6 Xposition Yposition Zposition Zrotation Xrotation Yrotation
  JOINT Arm
  {
    OFFSET 1 0 0
    CHANNELS 3 Yrotation Xrotation Zrotation
    End Site
    {
      OFFSET 0 2 0
    }
  }
  JOINT Leg
  {
    OFFSET 0 -1 0
    CHANNELS 3 Xrotation Yrotation Zrotation
    End Site
    {
      OFFSET 0 -3 0
    }
  }
}
MOTION
Frames: 2
Frame Time: 0.05
0 0 0 0 0 0 0 0 0 0 0 0
1 2 3 0 0 90 0 0 90 90 0 0
"""


def test_parse_structure_and_channels():
    bvh = parse_bvh(SIMPLE)
    assert bvh.names == ("Hips", "Arm", "Leg")
    assert bvh.parents == (-1, 0, 0)
    assert bvh.channels[1] == ("Yrotation", "Xrotation", "Zrotation")
    assert bvh.channel_start == (0, 6, 9)
    assert len(bvh.end_sites) == 2 and bvh.end_sites[0][0] == 1
    np.testing.assert_allclose(bvh.end_sites[1][1], [0, -3, 0])
    assert bvh.motion.shape == (2, 12)
    assert bvh.fps == pytest.approx(20.0)


def test_forward_kinematics_hand_computed():
    bvh = parse_bvh(SIMPLE)
    pos, rot = forward_kinematics(bvh, return_rotations=True)
    np.testing.assert_array_equal(forward_kinematics(bvh), pos)  # positions by default
    # frame 0: rest pose
    np.testing.assert_allclose(pos[0], [[0, 0, 0], [1, 0, 0], [0, -1, 0]], atol=1e-12)
    # frame 1: root at (1,2,3) rotated 90 deg about +Y: x -> -z
    np.testing.assert_allclose(pos[1, 0], [1, 2, 3], atol=1e-12)
    np.testing.assert_allclose(pos[1, 1], [1, 2, 2], atol=1e-12)  # offset (1,0,0) -> (0,0,-1)
    np.testing.assert_allclose(pos[1, 2], [1, 1, 3], atol=1e-12)  # (0,-1,0) unchanged
    # Arm: Ry(0) Rx(0) Rz(90) in its own frame; world = Ry(90) Rz(90); end site (0,2,0)
    end = pos[1, 1] + rot[1, 1] @ np.array([0.0, 2.0, 0.0])
    # Rz(90) (0,2,0) = (-2,0,0); Ry(90) (-2,0,0) = (0,0,2)
    np.testing.assert_allclose(end, [1, 2, 4], atol=1e-12)
    # Leg: Rx(90) then Ry(90): end site (0,-3,0) -> Rx: (0,0,-3) -> Ry(90) root: (-3,0,0)
    leg_end = pos[1, 2] + rot[1, 2] @ np.array([0.0, -3.0, 0.0])
    np.testing.assert_allclose(leg_end, [1 - 3, 1, 3], atol=1e-12)


def test_channel_order_matters():
    # Zrot 90 then Xrot 90 (R = Rz Rx) differs from Xrot then Zrot (R = Rx Rz)
    def end_of(order):
        text = f"""HIERARCHY
ROOT A
{{
  OFFSET 0 0 0
  CHANNELS 3 {order}
  End Site
  {{
    OFFSET 0 1 0
  }}
}}
MOTION
Frames: 1
Frame Time: 0.1
90 90 0
"""
        bvh = parse_bvh(text)
        _, rot = forward_kinematics(bvh, return_rotations=True)
        return rot[0, 0] @ np.array([0.0, 1.0, 0.0])

    # Rz(90) Rx(90) Ry(0) (0,1,0): Rx -> (0,0,1), Rz leaves z -> (0,0,1)
    np.testing.assert_allclose(end_of("Zrotation Xrotation Yrotation"), [0, 0, 1], atol=1e-12)
    # Rx(90) Rz(90) (0,1,0): Rz -> (-1,0,0), Rx leaves x -> (-1,0,0)
    np.testing.assert_allclose(end_of("Xrotation Zrotation Yrotation"), [-1, 0, 0], atol=1e-12)


def test_position_channels_replace_offset_on_child():
    text = SIMPLE.replace(
        "CHANNELS 3 Yrotation Xrotation Zrotation",
        "CHANNELS 6 Xposition Yposition Zposition Yrotation Xrotation Zrotation",
    )
    lines = text.splitlines()
    lines[-2] = "0 0 0 0 0 0 5 0 0 0 0 0 0 0 0"
    lines[-1] = "0 0 0 0 0 0 1 0 0 0 0 0 0 0 0"
    bvh = parse_bvh("\n".join(lines) + "\n")
    pos = forward_kinematics(bvh)
    np.testing.assert_allclose(pos[:, 1], [[5, 0, 0], [1, 0, 0]])


MALFORMED = {
    "empty": ("", "empty"),
    "no hierarchy": (SIMPLE.replace("HIERARCHY", "HIERARCH"), "HIERARCHY"),
    "no motion": (SIMPLE.split("MOTION")[0], "MOTION"),
    "truncated": (SIMPLE.rsplit("\n", 2)[0] + "\n", "truncated"),
    "value count": (
        SIMPLE.replace("1 2 3 0 0 90 0 0 90 90 0 0", "1 2 3 0 0 90 0 0 90 90 0"),
        "11 values",
    ),
    "non-numeric": (SIMPLE.replace("1 2 3 0 0 90", "1 2 x 0 0 90"), "non-numeric"),
    "non-finite": (SIMPLE.replace("1 2 3 0 0 90", "1 2 nan 0 0 90"), "non-finite"),
    "unknown channel": (
        SIMPLE.replace("Xrotation Yrotation Zrotation", "Xrotation Yrotation Wrotation"),
        "unknown channel",
    ),
    "bad frames": (SIMPLE.replace("Frames: 2", "Frames: two"), "Frames"),
    "bad brace": (SIMPLE.replace("  JOINT Leg", "  JUNK Leg"), "unexpected"),
}


@pytest.mark.parametrize("case", sorted(MALFORMED))
def test_malformed_raises_with_file_and_line(case, tmp_path):
    text, needle = MALFORMED[case]
    path = tmp_path / f"{case.replace(' ', '_')}.bvh"
    path.write_text(text)
    with pytest.raises(MotionDataError) as info:
        read_bvh(path)
    msg = str(info.value)
    assert needle.lower() in msg.lower()
    assert str(path) in msg
    assert info.value.line is not None and info.value.line >= 1
    assert f"{path}:{info.value.line}:" in msg


def test_error_line_points_at_the_bad_frame(tmp_path):
    text = SIMPLE.replace("1 2 3 0 0 90", "1 2 x 0 0 90")
    path = tmp_path / "bad.bvh"
    path.write_text(text)
    with pytest.raises(MotionDataError) as info:
        read_bvh(path)
    assert info.value.line == text.splitlines().index("1 2 x 0 0 90 0 0 90 90 0 0") + 1


def test_missing_file():
    with pytest.raises(MotionDataError, match="not found"):
        read_bvh("/nonexistent/file.bvh")
