"""A tiny deterministic stand-in for ``motionflows.data.MotionDataset`` (no tests here)."""

import numpy as np

from motionflows.data.names import CONTROL_DIM, POSE_DIM


class FakeStandardizer:
    def __init__(self, d=POSE_DIM, c=CONTROL_DIM):
        self.pose_mean = np.linspace(-0.5, 0.5, d).astype(np.float32)
        self.pose_std = np.linspace(0.1, 0.3, d).astype(np.float32)
        self.control_mean = np.zeros(c, np.float32)
        self.control_std = np.full(c, 0.05, np.float32)

    @property
    def log_det_per_frame(self):
        return float(-np.sum(np.log(self.pose_std)))

    def normalize_pose(self, x):
        return (np.asarray(x) - self.pose_mean) / self.pose_std

    def denormalize_pose(self, x):
        return np.asarray(x) * self.pose_std + self.pose_mean

    def normalize_control(self, c):
        return (np.asarray(c) - self.control_mean) / self.control_std

    def denormalize_control(self, c):
        return np.asarray(c) * self.control_std + self.control_mean

    def to_dict(self):
        return {
            k: getattr(self, k).tolist()
            for k in ("pose_mean", "pose_std", "control_mean", "control_std")
        }


class FakeWindows:
    def __init__(self, pose, control):
        self.pose, self.control = pose, control
        self.take = np.array([f"take{i}" for i in range(len(pose))])


class FakeDataset:
    """Windows of a smooth AR-like process; ``nan_at`` batch indices of "train" hold NaN."""

    def __init__(self, n=24, window=8, seed=0, nan_at=()):
        rng = np.random.default_rng(seed)
        self.standardizer = std = FakeStandardizer()
        self.nan_at = set(nan_at)
        splits = {}
        for i, name in enumerate(("train", "val", "test")):
            c = rng.normal(size=(n, window, CONTROL_DIM)).astype(np.float32)
            z = np.cumsum(rng.normal(size=(n, window, POSE_DIM)), axis=1) * 0.3
            z[..., :3] += c.mean(-1, keepdims=True)
            pose = std.denormalize_pose(z).astype(np.float32)
            splits[name] = FakeWindows(pose, std.denormalize_control(c).astype(np.float32))
            del i
        self.train, self.val, self.test = splits["train"], splits["val"], splits["test"]
        self.info = {"source": "fake", "window": window}

    def split(self, name):
        return getattr(self, name)

    def summary(self):
        return f"fake, {len(self.train.pose)} training windows"

    def batch(self, split, batch_size, *, seed, index, standardized=True):
        ws = self.split(split)
        rng = np.random.default_rng([seed, index, ("train", "val", "test").index(split)])
        idx = rng.integers(0, len(ws.pose), batch_size)
        pose = self.standardizer.normalize_pose(ws.pose[idx]).astype(np.float32)
        control = self.standardizer.normalize_control(ws.control[idx]).astype(np.float32)
        if split == "train" and index in self.nan_at:
            pose = pose.copy()
            pose[0, 0, 0] = np.nan
        return {"pose": pose, "control": control}


class MinimalStandardizer:
    def __init__(self, inner):
        self.log_det_per_frame = inner.log_det_per_frame
        self.to_dict = inner.to_dict


class MinimalDataset:
    """Only what the issue promises of a dataset: ``batch`` and ``standardizer``
    (``log_det_per_frame``, ``to_dict``)."""

    def __init__(self, inner):
        self.batch = inner.batch
        self.standardizer = MinimalStandardizer(inner.standardizer)
