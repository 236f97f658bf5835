"""Look at motion: stick-figure GIFs (side + top view), frame grids and control plots.

Input is what the models produce: pose (T, 63) in metres in the root frame and control
(T, 3) (forward m/frame, sideways m/frame, turn rad/frame). The world trajectory is
integrated from the control (:func:`motionflows.data.features.world_from_features`), so a
sample and its ground truth driven by the same control walk the same path.

Matplotlib (Agg, no pyplot state) draws the frames and Pillow writes the GIF, subsampled to
at most 20 fps at a modest size. Left-side bones are blue, right-side red, spine black.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from motionflows.data.features import Clip, integrate_control, world_from_features
from motionflows.data.names import CONTROL_DIM, JOINT_NAMES, NUM_JOINTS, PARENTS, POSE_DIM

_COLORS = ["tab:blue" if n.startswith("Left") else "tab:red" if n.startswith("Right")
           else "black" for n in JOINT_NAMES]  # fmt: skip
_COMPARE_ALPHA = 0.45


def _check(pose, control, what="pose") -> tuple[np.ndarray, np.ndarray]:
    pose = np.asarray(pose, dtype=np.float64)
    control = np.asarray(control, dtype=np.float64)
    if pose.ndim != 2 or pose.shape[1] != POSE_DIM:
        raise ValueError(f"{what} must be (T, {POSE_DIM}) metres, got {pose.shape}")
    if control.ndim != 2 or control.shape[1] != CONTROL_DIM or len(control) < len(pose):
        raise ValueError(
            f"control must be (T, {CONTROL_DIM}) with T >= {len(pose)}, got {control.shape}"
        )
    if not (np.isfinite(pose).all() and np.isfinite(control).all()):
        raise ValueError(f"{what} or control has non-finite values")
    if np.abs(pose).max() > 50:
        raise ValueError(
            f"{what} values exceed 50 m: pass metres (centimetre data? standardised data? "
            "use standardizer.denormalize_pose first)"
        )
    return pose, control[: len(pose)]


def _figure(ncols: int, width: float = 3.2, height: float = 3.2):
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=(width * ncols, height))
    FigureCanvasAgg(fig)
    return fig


def _draw_skeleton(ax, pts2d, alpha=1.0, lw=2.0):
    for j, p in enumerate(PARENTS):
        if p >= 0:
            ax.plot(pts2d[[p, j], 0], pts2d[[p, j], 1], color=_COLORS[j], lw=lw, alpha=alpha)


def _side_points(pose_t: np.ndarray, shift: float = 0.0) -> np.ndarray:
    """Side view in the character's own root frame: horizontal = forward (z), vertical = y."""
    p = pose_t.reshape(NUM_JOINTS, 3)
    return np.stack([p[:, 2] + shift, p[:, 1]], -1)


def _world(pose, control):
    world = world_from_features(pose, control)
    root, _ = integrate_control(control)
    return world, root


def _rgb(fig) -> np.ndarray:
    fig.canvas.draw()
    return np.asarray(fig.canvas.buffer_rgba())[..., :3].copy()


class _Stage:
    """One figure with side and top panels whose artists are updated per frame."""

    def __init__(self, poses, worlds, root, title, dpi):
        self.poses, self.worlds, self.root, self.title = poses, worlds, root, title
        self.fig = _figure(2)
        self.fig.set_dpi(dpi)
        side, top = self.fig.subplots(1, 2)
        two = len(poses) > 1
        side.axhline(0.0, color="0.6", lw=1)
        side.set_xlim(-1.2, 1.2 + (1.0 if two else 0.0))
        side.set_ylim(-0.05, 2.0)
        side.set_aspect("equal")
        side.set_title(
            "side, root frame (forward, up)" + (": right = compare" if two else ""), fontsize=8
        )
        top.plot(root[:, 0], root[:, 2], color="0.5", lw=1)
        lo = root[:, [0, 2]].min(0) - 1.0
        hi = root[:, [0, 2]].max(0) + 1.0
        span, mid = max(hi - lo) / 2, (hi + lo) / 2
        top.set_xlim(mid[0] + span, mid[0] - span)  # +x (left of a +z walker) drawn left
        top.set_ylim(mid[1] - span, mid[1] + span)
        top.set_aspect("equal")
        top.set_title("top (x, z); path integrated from control", fontsize=8)
        for ax in (side, top):
            ax.tick_params(labelsize=6)
        self.side_lines, self.top_lines = [], []
        for k in range(len(poses)):
            alpha = 1.0 if k == 0 else _COMPARE_ALPHA
            self.side_lines.append(
                [
                    side.plot([], [], color=_COLORS[j], lw=2, alpha=alpha)[0]
                    for j in range(NUM_JOINTS)
                ]
            )
            self.top_lines.append(
                [
                    top.plot([], [], color=_COLORS[j], lw=1.2, alpha=alpha)[0]
                    for j in range(NUM_JOINTS)
                ]
            )
        (self.marker,) = top.plot([], [], "o", color="tab:green", ms=4)
        self.suptitle = self.fig.suptitle("", fontsize=9)

    def frame(self, t: int, fps: float) -> np.ndarray:
        for k, (pose, world) in enumerate(zip(self.poses, self.worlds, strict=True)):
            side = _side_points(pose[t], 1.0 if k else 0.0)
            top = world[t][:, [0, 2]]
            for j, p in enumerate(PARENTS):
                if p >= 0:
                    self.side_lines[k][j].set_data(side[[p, j], 0], side[[p, j], 1])
                    self.top_lines[k][j].set_data(top[[p, j], 0], top[[p, j], 1])
        self.marker.set_data([self.root[t, 0]], [self.root[t, 2]])
        self.suptitle.set_text(f"{self.title or ''}  t={t / fps:.2f}s".strip())
        return _rgb(self.fig)


def animate(
    pose,
    control,
    path,
    *,
    fps: float = 20.0,
    title: str | None = None,
    compare=None,
    max_fps: float = 20.0,
    dpi: int = 60,
) -> Path:
    """Write a stick-figure GIF of pose (T, 63) metres driven by control (T, 3).

    Left panel: the character in its root frame seen from its left side (forward to the
    right). Right panel: top view of the world, path integrated from the control.
    ``compare``: an optional second pose sequence (T', 63) drawn beside (faded, shifted
    1 m), moved along the same control (e.g. ground truth vs sample). Frames are
    subsampled to at most ``max_fps``.
    """
    from PIL import Image

    pose, control = _check(pose, control)
    poses = [pose]
    if compare is not None:
        poses.append(_check(compare, control, "compare")[0])
    n = min(len(p) for p in poses)
    worlds = [_world(p[:n], control[:n])[0] for p in poses]
    root, _ = integrate_control(control[:n])
    stage = _Stage([p[:n] for p in poses], worlds, root, title, dpi)
    step = max(1, int(np.ceil(fps / max_fps)))
    frames = [
        Image.fromarray(stage.frame(t, fps)).convert("P", palette=Image.ADAPTIVE, colors=32)
        for t in range(0, n, step)
    ]
    out = Path(path)
    out.parent.mkdir(parents=True, exist_ok=True)
    frames[0].save(
        out,
        save_all=True,
        append_images=frames[1:],
        duration=int(round(1000 * step / fps)),
        loop=0,
        optimize=True,
    )
    return out


def frame_grid(
    pose, control, path, *, n: int = 6, fps: float = 20.0, title: str | None = None, dpi: int = 70
) -> Path:
    """A PNG with ``n`` evenly spaced side views plus the top-view trajectory."""
    pose, control = _check(pose, control)
    world, root = _world(pose, control)
    idx = np.linspace(0, len(world) - 1, n).round().astype(int)
    fig = _figure(n + 1, width=2.0, height=3.0)
    axes = fig.subplots(1, n + 1)
    for ax, t in zip(axes[:-1], idx, strict=True):
        _draw_skeleton(ax, _side_points(pose[t]))
        ax.axhline(0.0, color="0.6", lw=1)
        ax.set_xlim(-1, 1)
        ax.set_ylim(-0.05, 2.0)
        ax.set_aspect("equal")
        ax.set_title(f"t={t / fps:.1f}s", fontsize=7)
        ax.tick_params(labelsize=5)
    top = axes[-1]
    top.plot(root[:, 0], root[:, 2], color="0.5")
    for t in idx:
        _draw_skeleton(top, world[t][:, [0, 2]], lw=0.8)
    top.set_aspect("equal")
    top.invert_xaxis()
    top.set_title("top (x, z)", fontsize=7)
    top.tick_params(labelsize=5)
    if title:
        fig.suptitle(title, fontsize=8)
    out = Path(path)
    out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out, dpi=dpi)
    return out


def plot_controls(control, path, fps: float = 20.0, *, title: str | None = None) -> Path:
    """PNG of forward / sideways speed (m/s) and turn rate (deg/s) against time."""
    control = np.asarray(control, dtype=np.float64)
    if control.ndim != 2 or control.shape[1] != CONTROL_DIM:
        raise ValueError(f"control must be (T, {CONTROL_DIM}), got {control.shape}")
    t = np.arange(len(control)) / fps
    fig = _figure(1, width=6.0, height=4.0)
    axes = fig.subplots(3, 1, sharex=True)
    series = [
        (control[:, 0] * fps, "forward (m/s)"),
        (control[:, 1] * fps, "sideways (m/s, +left)"),
        (np.degrees(control[:, 2]) * fps, "turn (deg/s, +left)"),
    ]
    for ax, (y, label) in zip(axes, series, strict=True):
        ax.plot(t, y, lw=1.2)
        ax.axhline(0, color="0.7", lw=0.8)
        ax.set_ylabel(label, fontsize=7)
        ax.tick_params(labelsize=6)
    axes[-1].set_xlabel("time (s)", fontsize=7)
    if title:
        fig.suptitle(title, fontsize=8)
    out = Path(path)
    out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out, dpi=80)
    return out


def render_clip(clip: Clip, out_dir: str | os.PathLike, *, compare=None) -> dict[str, Path]:
    """``<name>.gif`` and ``<name>_controls.png`` of a :class:`Clip` in ``out_dir``."""
    out = Path(out_dir)
    name = clip.name.replace(os.sep, "_")
    return {
        "gif": animate(
            clip.pose,
            clip.control,
            out / f"{name}.gif",
            fps=clip.fps,
            title=clip.name,
            compare=compare,
        ),
        "controls": plot_controls(
            clip.control, out / f"{name}_controls.png", clip.fps, title=clip.name
        ),
    }


__all__ = ["animate", "frame_grid", "plot_controls", "render_clip", "NUM_JOINTS"]
