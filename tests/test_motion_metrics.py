"""Motion metrics: root integration conventions, prediction errors, quality metrics."""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np
import pytest

from motionflows.data.names import NUM_JOINTS, PARENTS, POSE_DIM
from motionflows.evaluation import motion as M


def _stand(n: int = 1, t: int = 10, seed: int = 0) -> np.ndarray:
    """A rigid random skeleton with feet on the floor, same every frame: (n, t, 63)."""
    rng = np.random.default_rng(seed)
    j = rng.normal(size=(NUM_JOINTS, 3)) * 0.3
    j[:, 1] = np.abs(j[:, 1]) + 0.2
    j[[3, 4, 7, 8], 1] = 0.01  # feet on the ground
    return np.broadcast_to(j.reshape(-1), (n, t, POSE_DIM)).copy()


def test_integrate_root_conventions():
    t = 5
    walk = np.zeros((t, 3))
    walk[:, 0] = 1.0  # forward 1 m/frame
    pos, yaw = M.integrate_root(walk)
    np.testing.assert_allclose(pos[:, 2], np.arange(t))  # along +z
    np.testing.assert_allclose(pos[:, [0, 1]], 0.0)
    np.testing.assert_allclose(yaw, 0.0)

    side = np.zeros((t, 3))
    side[:, 1] = 1.0  # sideways + = left = +x
    pos, _ = M.integrate_root(side)
    np.testing.assert_allclose(pos[:, 0], np.arange(t))

    # a +90 degree (counter-clockwise, left) turn, then forward: moves towards +x
    turn = np.zeros((3, 3))
    turn[0, 2] = np.pi / 2
    turn[1, 0] = 1.0
    pos, yaw = M.integrate_root(turn)
    np.testing.assert_allclose(yaw, [0.0, np.pi / 2, np.pi / 2], atol=1e-12)
    np.testing.assert_allclose(pos[-1], [1.0, 0.0, 0.0], atol=1e-12)


def test_integrate_root_inverts_control_definition():
    """Controls computed from a random world trajectory (displacement in the root frame of
    t, heading change) integrate back to that trajectory."""
    rng = np.random.default_rng(1)
    t = 30
    yaw = np.cumsum(rng.normal(size=t) * 0.2)
    yaw -= yaw[0]
    p = np.cumsum(rng.normal(size=(t, 2)), axis=0)
    p -= p[0]
    d = p[1:] - p[:-1]
    fwd = d[:, 0] * np.sin(yaw[:-1]) + d[:, 1] * np.cos(yaw[:-1])
    side = d[:, 0] * np.cos(yaw[:-1]) - d[:, 1] * np.sin(yaw[:-1])
    ctl = np.zeros((t, 3))
    ctl[:-1] = np.stack([fwd, side, np.diff(yaw)], -1)
    pos, yaw_hat = M.integrate_root(ctl)
    np.testing.assert_allclose(pos[:, [0, 2]], p, atol=1e-9)
    np.testing.assert_allclose(yaw_hat, yaw, atol=1e-9)
    # jax arrays give the same answer
    pos_j, _ = M.integrate_root(jnp.asarray(ctl, jnp.float32))
    np.testing.assert_allclose(np.asarray(pos_j)[:, [0, 2]], p, atol=1e-3)


def test_to_global_rotates_about_y_and_keeps_heights():
    pose = np.zeros((3, POSE_DIM))
    pose[:, 3:6] = [0.0, 1.0, 1.0]  # joint 1: 1 m up, 1 m in front
    ctl = np.zeros((3, 3))
    ctl[0, 2] = np.pi / 2  # turn left after frame 0
    w = M.to_global(pose, ctl).reshape(3, NUM_JOINTS, 3)
    np.testing.assert_allclose(w[0, 1], [0.0, 1.0, 1.0], atol=1e-12)
    np.testing.assert_allclose(w[1, 1], [1.0, 1.0, 0.0], atol=1e-12)  # in front = +x now
    with pytest.raises(ValueError, match="same number of frames"):
        M.to_global(pose, ctl[:2])
    with pytest.raises(ValueError, match="63"):
        M.to_global(pose[:, :60], ctl)


def test_prediction_frames_and_errors():
    assert M.prediction_frames(60) == (70, 90, 120, 160, 210)
    assert M.prediction_frames(20) == (23, 30, 40, 53, 70)
    with pytest.raises(ValueError, match="longer test windows"):
        M.prediction_frames(20, window=64)

    rng = np.random.default_rng(0)
    n, t = 4, 80
    target = rng.normal(size=(n, t, POSE_DIM))
    ctl = rng.normal(size=(n, t, 3)) * 0.1
    # shifting every joint (including the root joint) by the same offset: zero pose error
    # (root-relative) but a motion error equal to the offset's length
    offset = np.tile([0.3, 0.0, 0.4], NUM_JOINTS)
    pred = target + offset
    np.testing.assert_allclose(M.pose_error(pred, target), 0.0, atol=1e-12)
    np.testing.assert_allclose(M.motion_error(pred, target, ctl), 0.5, atol=1e-12)
    # moving one non-root joint by 0.2 m: pose error 0.2 / 20 joints at every frame
    pred = target.copy()
    pred[..., 6] += 0.2
    np.testing.assert_allclose(M.pose_error(pred, target), 0.2 / 20, atol=1e-12)
    # samples axis averages; a different trajectory adds motion error but no pose error
    other = ctl.copy()
    other[:, :, 0] += 0.1
    out = M.prediction_errors(np.stack([target, target]), target, ctl, fps=20, pred_control=other)
    assert out["frames"] == [23, 30, 40, 53, 70] and out["num_samples"] == 2
    np.testing.assert_allclose(out["pose_error"], 0.0, atol=1e-12)
    assert np.all(np.diff(out["motion_error"]) > 0)  # the drift grows with time
    with pytest.raises(ValueError, match="pred must have shape"):
        M.pose_error(target[:, :10], target)


def test_foot_sliding_contact_and_bones():
    fps = 20.0
    pose = _stand(2, 12)
    still = np.zeros((2, 12, 3))
    assert M.foot_sliding(pose, still, fps=fps) == pytest.approx(0.0, abs=1e-12)
    assert M.contact_rate(pose) == 1.0
    # moving the root forward with planted (root-frame-fixed) feet slides them at 1 m/frame
    moving = still.copy()
    moving[..., 0] = 0.05
    assert M.foot_sliding(pose, moving, fps=fps) == pytest.approx(0.05 * fps)
    lifted = pose.copy()
    lifted[..., [10, 13, 22, 25]] = 0.5  # every foot joint's height 0.5 m: no contact
    assert M.foot_sliding(lifted, moving, fps=fps) == 0.0
    assert M.contact_rate(lifted) == 0.0

    assert M.bone_length_variation(pose) == pytest.approx(0.0, abs=1e-12)
    stretched = pose.copy()
    stretched[:, ::2, 3 * 2 : 3 * 2 + 3] *= 1.5  # the left knee jumps every other frame
    assert M.bone_length_variation(stretched) > 1e-3
    assert M.bone_lengths(pose).shape == (2, 12, sum(p >= 0 for p in PARENTS))


def test_jerk_frechet_diversity():
    fps = 20.0
    pose = _stand(1, 20)
    assert M.jerk(pose, fps=fps) == pytest.approx(0.0, abs=1e-9)
    # constant acceleration in the world has zero jerk; a cubic has constant jerk
    t = np.arange(20) / fps
    ctl = np.zeros((1, 20, 3))
    ctl[0, :, 0] = np.diff(t**3, append=(20 / fps) ** 3)  # forward position = t^3
    assert M.jerk(pose, fps=fps, control=ctl) == pytest.approx(6.0, rel=1e-6)

    rng = np.random.default_rng(0)
    a = rng.normal(size=(4000, 5))
    assert M.frechet_distance(a, a) == pytest.approx(0.0, abs=1e-6)
    # Gaussians N(0, I) and N(m, 4 I) in 5 dims: |m|^2 + 5 (1 + 4 - 2 * 2) = |m|^2 + 5
    b = 2.0 * rng.normal(size=(4000, 5)) + 1.0
    assert M.frechet_distance(a, b) == pytest.approx(5.0 + 5.0, rel=0.1)
    real = np.cumsum(rng.normal(size=(40, 10, POSE_DIM)), axis=1)  # smooth in time
    assert M.frechet_pose_distance(real, real) == pytest.approx(0.0, abs=1e-6)
    shuffled = real[:, rng.permutation(10)]  # same poses, scrambled in time
    assert M.frechet_pose_distance(real, shuffled) == pytest.approx(0.0, abs=1e-6)
    # ... but the statistics of 3-frame windows see the lost temporal correlation
    assert M.frechet_window_distance(real, shuffled) > 10.0
    assert M.frechet_window_distance(real, real) == pytest.approx(0.0, abs=1e-6)
    assert M.pose_features(real, frames=3).shape == (40 * 8, 3 * POSE_DIM)

    same = np.stack([real, real, real])
    assert M.diversity(same) == 0.0
    spread = np.stack([real, real + np.tile([0.0, 0.0, 0.3], NUM_JOINTS)])
    assert M.diversity(spread) == pytest.approx(0.3)
    with pytest.raises(ValueError, match="S >= 2"):
        M.diversity(real[None])
    q = M.motion_quality(pose, np.zeros((1, 20, 3)), fps=fps)
    assert set(q) == {"foot_sliding", "contact_rate", "bone_length_std", "jerk"}
