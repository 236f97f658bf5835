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
    assert M.skate_ratio(pose, moving, fps=fps) == 1.0  # 1 m/s > 0.5 m/s at every step
    lifted = pose.copy()
    lifted[..., [10, 13, 22, 25]] = 0.5  # every foot joint's height 0.5 m: no contact
    assert M.foot_sliding(lifted, moving, fps=fps) == 0.0
    assert M.contact_rate(lifted) == 0.0  # a floating character defines no floor of its own
    # the old rule (5 cm above y = 0) is kept for comparison with earlier reports
    assert M.contact_rate(pose, rule="absolute") == 1.0
    low = pose.copy()
    low[..., [10, 13, 22, 25]] = 0.04
    assert M.contact_rate(low, rule="absolute") == 1.0
    assert M.contact_rate(low, rule="absolute", contact_height=0.03) == 0.0
    with pytest.raises(ValueError, match="unknown contact rule"):
        M.contact_rate(pose, rule="speed")

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
    assert set(q) == {"foot_sliding", "skate_ratio", "contact_rate", "bone_length_std", "jerk"}


def _planted_walk(t: int = 80, speed: float = 0.06, period: int = 20) -> tuple:
    """Straight walking along +z with world-fixed stance feet: (pose (1, t, 63), control).

    Each foot stands still for half of every ``period`` frames and swings (lifted up to
    10 cm, moving at twice the root speed) for the other half, the feet in antiphase."""
    body = _stand(1, 1)[0, 0].reshape(NUM_JOINTS, 3)
    root_z = speed * np.arange(t)
    world = np.broadcast_to(body, (t, NUM_JOINTS, 3)).copy()
    world[:, :, 2] += root_z[:, None]
    half = period // 2
    for joints, offset in (((3, 4), 0), ((7, 8), half)):
        k = np.arange(t) + offset
        phase, cycle = k % period, k // period
        swing = phase >= half
        s = np.where(swing, (phase - half + 1) / half, 0.0)  # swing progress in (0, 1]
        foot_z = speed * period * (cycle + s) - speed * offset
        lift = 0.1 * np.sin(np.pi * s)
        for j in joints:
            world[:, j, 2] = foot_z + body[j, 2]
            world[:, j, 1] = body[j, 1] + lift
    pose = world.copy()
    pose[:, :, 2] -= root_z[:, None]  # root frame (no turning: yaw 0)
    control = np.zeros((1, t, 3))
    control[..., 0] = speed
    return pose.reshape(1, t, POSE_DIM), control


def test_contact_rule_planted_feet_and_dragged_pose():
    fps = 20.0
    pose, control = _planted_walk()
    assert M.foot_sliding(pose, control, fps=fps) == pytest.approx(0.0, abs=1e-9)
    assert M.skate_ratio(pose, control, fps=fps) == 0.0
    assert 0.3 <= M.contact_rate(pose) <= 0.7  # stance half of the time
    contacts = M.foot_contacts(pose)
    assert contacts.shape == (1, 80, 2)
    assert not (contacts[0, :, 0] & contacts[0, :, 1]).all()  # the feet alternate
    # the same walk raised 3 cm (a floor the data estimate finds) is still planted ...
    raised = pose.copy()
    raised[..., 1::3] += 0.03
    assert M.foot_sliding(raised, control, fps=fps) == pytest.approx(0.0, abs=1e-9)
    # ... while freezing the first pose and dragging it along the path slides at root speed
    frozen = np.broadcast_to(pose[:, :1], pose.shape).copy()
    assert M.foot_sliding(frozen, control, fps=fps) == pytest.approx(0.06 * fps, rel=1e-9)
    assert M.contact_rate(frozen) > 0.0


def test_natural_diversity_pairs_nearest_controls():
    walk, run = np.zeros((10, 3)), np.zeros((10, 3))
    walk[:, 0], run[:, 0] = 0.05, 0.15
    nudge = np.array([1e-3, 0.0, 0.0])  # a slightly faster copy of each
    control = np.stack([walk, walk + nudge, run, run + nudge])
    base = _stand(1, 10)[0]
    shift = np.tile([0.0, 0.0, 1.0], NUM_JOINTS)
    pose = np.stack([base, base + 0.2 * shift, base, base + 0.4 * shift])
    # walk pairs with walk (0.2 m apart), run with run (0.4 m): mean 0.3 m
    assert M.natural_diversity(pose, control) == pytest.approx(0.3)
    assert M.natural_diversity(pose, control, takes=np.array(["a", "b", "a", "b"])) == (
        pytest.approx(0.3)
    )
    # neighbours come from another take: with both walks in take a, a walk pairs with a run
    # (0 -> 2 is closest: 0 m; 1 -> 2: 0.2 m; 2 -> 1: 0.2 m; 3 -> 1: 0.2 m)
    takes = np.array(["a", "a", "b", "b"])
    assert M.natural_diversity(pose, control, takes=takes) == pytest.approx(0.15)
    with pytest.raises(ValueError, match="two takes"):
        M.natural_diversity(pose, control, takes=np.array(["a"] * 4))


def test_nearest_control_weighs_each_channel_by_its_spread_in_the_pool():
    # the pool's forward speed spreads over 1 m/frame, its turn over 0.01 rad/frame: a turn
    # off by 0.01 is a larger difference than a forward speed off by 0.02
    rng = np.random.default_rng(0)
    pool = np.zeros((6, 8, 3))
    pool[:, :, 0] = rng.uniform(-1.5, 1.5, size=(6, 1))
    pool[:, :, 2] = rng.uniform(-0.015, 0.015, size=(6, 1))
    query = pool[:1].copy()
    pool[1] = query[0] + [0.0, 0.0, 0.01]  # unscaled, 1e-4 per frame away
    pool[2] = query[0] + [0.02, 0.0, 0.0]  # unscaled, 4e-4 per frame away
    pool = pool[1:]  # the query itself is not in the pool
    assert M.nearest_control(query, pool).tolist() == [1]  # pool[2] above
    unscaled = ((query.reshape(1, -1) - pool.reshape(len(pool), -1)) ** 2).sum(1)
    assert np.argmin(unscaled) == 0  # plain distances would pick the turn's neighbour
    # squared distances in the pool's std units, so the pool holds every query at 0
    d = M.control_distances(pool, pool)
    np.testing.assert_allclose(np.diag(d), 0.0, atol=1e-9)
    assert M.nearest_control(pool, pool).tolist() == list(range(len(pool)))
    with pytest.raises(ValueError, match="same T"):
        M.control_distances(query, pool[:, :4])


def test_stride_period_finds_the_feet_alternation_and_not_its_multiples():
    """Ankles swinging in anti-phase with period P (plus noise): the estimate is P, for any
    amplitude, within 2 %; standing gives NaN; the synthetic walk's rises with slower speed."""
    from motionflows.data.names import FOOT_JOINTS
    from motionflows.data.synthetic import straight_walk

    fps, t = 20.0, 80
    rng = np.random.default_rng(0)
    pose = np.zeros((4, t, NUM_JOINTS, 3))
    periods = np.array([0.6, 0.9, 1.13, 1.4])
    for n, (period, amp) in enumerate(zip(periods, [0.1, 0.3, 0.5, 0.2], strict=True)):
        swing = amp * np.sin(2 * np.pi * np.arange(t) / fps / period + n)
        pose[n, :, FOOT_JOINTS[0], 2] = swing
        pose[n, :, FOOT_JOINTS[2], 2] = -swing
    pose += rng.normal(0, 0.01, pose.shape)
    got = M.stride_period(pose.reshape(4, t, POSE_DIM), fps=fps)
    assert np.allclose(got, periods, rtol=0.02), got
    standing = M.stride_period(rng.normal(0, 1e-3, (1, t, POSE_DIM)), fps=fps)
    assert np.isnan(standing).all()
    slow, fast = (straight_walk(v, seconds=4.0) for v in (0.8, 1.6))
    assert M.stride_period(slow.pose[None], fps=fps) > 1.2 * M.stride_period(
        fast.pose[None], fps=fps
    )
    # a window too short for any lag is one clear error (it was an IndexError), naming the
    # frames needed: a peak needs three lags from shortest * fps up to T / 2
    with pytest.raises(ValueError, match=r"needs at least 24 frames, got 10"):
        M.stride_period(pose[:1, :10].reshape(1, 10, POSE_DIM), fps=fps)
    M.stride_period(pose[:1, :24].reshape(1, 24, POSE_DIM), fps=fps)  # enough: no error


def test_contact_metrics_refuse_non_finite_input():
    """A NaN in one frame used to make foot_sliding NaN while skate_ratio and contact_rate
    counted the frame as 'no contact' and returned a clean-looking number."""
    pose, control = _stand(2, 12), np.zeros((2, 12, 3))
    bad_pose = pose.copy()
    bad_pose[1, 5, 0] = np.nan  # the hips' x: not a foot, so no contact test touches it
    bad_control = control.copy()
    bad_control[0, 3, 2] = np.inf
    for metric in (M.foot_sliding, M.skate_ratio):
        metric(pose, control, fps=20.0)
        with pytest.raises(ValueError, match="pose contains non-finite values.*diverged"):
            metric(bad_pose, control, fps=20.0)
        with pytest.raises(ValueError, match="control contains non-finite values"):
            metric(pose, bad_control, fps=20.0)
    with pytest.raises(ValueError, match="pose contains non-finite values"):
        M.contact_rate(bad_pose)
    with pytest.raises(ValueError, match="pose contains non-finite values"):
        M.motion_quality(bad_pose, control, fps=20.0)
