"""Look at motion: world-space stick-figure GIFs and PNG stills, frame grids, control plots.

Input is what the models produce: pose (T, 63) in metres in the root frame (y up, the
character faces +z, +x is its left) and control (T, 3) (forward m/frame, sideways m/frame,
turn rad/frame). The root's world path is integrated from the control and each pose placed
on it (:func:`motionflows.evaluation.motion.integrate_root` / ``to_global``), so a sample
and its ground truth driven by the same control walk the same path.

An animation frame is a matplotlib 3D view (mplot3d, perspective) that follows the root,
22 degrees above the floor, looking at the character from its right-front (it swings with
the character's facing, smoothed, see :func:`_camera_azimuths`):

* the floor y = 0 as a 0.5 m grid, the walked path (green), the skeleton's shadow on the
  floor (grey: a floating foot is the gap between a foot and its shadow);
* foot contacts, decided as the foot-sliding metric does
  (:func:`motionflows.evaluation.motion.foot_contacts`, height only): the touching joint is
  ringed and the foot leaves a footprint (its centre, whose speed that metric averages) on
  the floor, so a planted foot leaves one dot and a sliding foot a streak;
* with ``compare`` (e.g. the ground truth) a second panel with the same camera, following
  the same path. Two panels rather than one shifted figure: a sideways shift that follows
  the root's heading would drag the shifted figure around every turn (fake sliding), and a
  fixed world shift puts it in front of or behind the walker after a turn.

Matplotlib (Agg, no pyplot state) draws the frames into one figure whose artists are updated
per frame, and Pillow writes the GIF, subsampled to at most 20 fps. Left-side bones are
blue, right-side red, spine black.
"""

from __future__ import annotations

import os
import warnings
from pathlib import Path

import numpy as np

from motionflows.data.features import Clip
from motionflows.data.names import (
    CONTROL_DIM,
    FOOT_JOINTS,
    JOINT_NAMES,
    NUM_JOINTS,
    PARENTS,
    POSE_DIM,
)
from motionflows.evaluation.motion import foot_contacts, integrate_root, to_global

_COLORS = ["tab:blue" if n.startswith("Left") else "tab:red" if n.startswith("Right")
           else "black" for n in JOINT_NAMES]  # fmt: skip
_BONES = [(p, j) for j, p in enumerate(PARENTS) if p >= 0]
_GRID_STEP = 0.5  # m between floor grid lines
_VIEW_HALF = 2.0  # m: the camera shows the root +- this on the floor
_VIEW_HEIGHT = 1.5  # m
_ELEVATION = 22.0  # degrees above the floor
_ZOOM = 2.1  # mplot3d box zoom: the character fills about 3/4 of the picture's height
_PANEL_INCHES = (6.4, 4.8)  # one panel; 640 x 480 px at dpi 100 (two: 512 px wide each)
MAX_GIF_SECONDS = 120.0
""":func:`animate` draws at most this many seconds of motion (the first ones, with a
warning): a GIF's frames are held in memory until it is written (~0.6 MB a frame at 20 fps,
~1.5 GB for 2 minutes) and drawn at ~40 frames/s."""


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
    for p, j in _BONES:
        ax.plot(pts2d[[p, j], 0], pts2d[[p, j], 1], color=_COLORS[j], lw=lw, alpha=alpha)


def _side_points(pose_t: np.ndarray, shift: float = 0.0) -> np.ndarray:
    """Side view in the character's own root frame: horizontal = forward (z), vertical = y."""
    p = pose_t.reshape(NUM_JOINTS, 3)
    return np.stack([p[:, 2] + shift, p[:, 1]], -1)


def world_joints(pose, control) -> np.ndarray:
    """World joint positions (T, 21, 3) metres of pose (T, 63) on the path of control (T, 3):
    :func:`motionflows.evaluation.motion.to_global`, frame 0's root at the origin facing +z."""
    pose, control = _check(pose, control)
    return to_global(pose, control).reshape(len(pose), NUM_JOINTS, 3)


def _contact_marks(world: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Where to draw the foot contacts of world joints (T, 21, 3).

    Contact is :func:`motionflows.evaluation.motion.foot_contacts` (its default height-only
    rule, the one the foot-sliding metric uses). Returns, per foot (left, right), the
    contacting joint (T, 2, 3) (the foot's lower one, ankle or toe; NaN when not in contact)
    and the footprint (T, 2, 3): the foot centre (mean of ankle and toe, whose speed is the
    metric's sliding speed) on the floor y = 0, NaN when not in contact.
    """
    contact = foot_contacts(world.reshape(len(world), -1))  # (T, 2); heights need no yaw
    ankle, toe = world[:, list(FOOT_JOINTS[::2])], world[:, list(FOOT_JOINTS[1::2])]
    low = np.where((toe[..., 1] < ankle[..., 1])[..., None], toe, ankle)
    prints = 0.5 * (ankle + toe) * np.array([1.0, 0.0, 1.0])
    off = ~contact[..., None]
    return np.where(off, np.nan, low), np.where(off, np.nan, prints)


def _camera_azimuths(yaw: np.ndarray, fps: float) -> np.ndarray:
    """Per-frame camera azimuth (T,) degrees (matplotlib's, with y up) from the root's yaw
    (T,) radians: the camera looks at the character from its right-front, 70 degrees right of
    its facing, so strides are seen nearly side-on and a forward walk moves to the right of
    the picture (a backward walk to the left). The yaw is averaged over +-1 s so the camera
    swings smoothly through turns and ignores the root's jitter."""
    w = max(1, int(round(fps)))
    smooth = np.convolve(np.pad(yaw, w, mode="edge"), np.ones(2 * w + 1) / (2 * w + 1), "valid")
    # with vertical_axis="y" matplotlib's azimuth a puts the camera towards (x, z) =
    # (sin a, cos a) from the centre, i.e. it is a yaw like the control's turn
    return np.degrees(smooth - np.radians(70.0))


def _finite(points: np.ndarray) -> np.ndarray:
    return points[np.isfinite(points).all(-1)]


class _Stage:
    """One figure with a 3D panel per character; artists are updated per frame."""

    def __init__(self, worlds, root, yaw, fps, *, title=None, labels=None, dpi=100.0):
        from mpl_toolkits.mplot3d.art3d import Line3DCollection

        self.worlds, self.root, self.title = worlds, root, title
        self.marks = [_contact_marks(w) for w in worlds]
        n = len(worlds)
        width, height = _PANEL_INCHES
        if n > 1:  # two panels side by side, each a little narrower than a lone one
            width *= 0.8
        self.fig = _figure(n, width=width, height=height)
        self.fig.set_dpi(dpi)
        self.azimuths = _camera_azimuths(yaw, fps)
        self.panels = []
        for k in range(n):
            # a 3D axes is always square: make it as wide as its column (cropped at the top
            # and bottom of the figure) so that the floor fills the picture's width
            tall = width / height
            ax = self.fig.add_axes(
                (k / n, 0.5 - tall / 2, 1 / n, tall), projection="3d", computed_zorder=False
            )
            ax.set_axis_off()
            ax.set_proj_type("persp", focal_length=0.6)
            ax.view_init(elev=_ELEVATION, azim=self.azimuths[0], vertical_axis="y")
            ax.set_box_aspect((2 * _VIEW_HALF, _VIEW_HEIGHT, 2 * _VIEW_HALF), zoom=_ZOOM)
            if labels is not None:
                self.fig.text((k + 0.5) / n, 0.93, labels[k], ha="center", fontsize=9)
            panel = {"ax": ax}
            panel["grid"] = Line3DCollection([], colors="0.8", lw=0.8, zorder=1)
            (panel["path"],) = ax.plot(
                root[:, 0], root[:, 1], root[:, 2], color="tab:green", lw=1.5, alpha=0.8,
                axlim_clip=True, zorder=2,
            )  # fmt: skip
            panel["prints"] = [
                ax.plot([], [], [], "o", ms=4, color=_COLORS[j], alpha=0.5, mew=0,
                        axlim_clip=True, zorder=3)[0]
                for j in FOOT_JOINTS[::2]
            ]  # fmt: skip
            panel["shadow"] = Line3DCollection([], colors="0.65", lw=2.5, alpha=0.6, zorder=4)
            panel["bones"] = Line3DCollection(
                [], colors=[_COLORS[j] for _, j in _BONES], lw=2.5, zorder=5
            )
            (panel["marks"],) = ax.plot(
                [], [], [], "o", ms=9, mfc="none", mec="tab:orange", mew=2, zorder=6
            )
            for key in ("grid", "shadow", "bones"):
                ax.add_collection3d(panel[key], autolim=False)
            self.panels.append(panel)
        self.fig.text(
            0.01,
            0.012,
            "orange ring: foot on the floor; dots: its footprints, a slide smears them; "
            "grey: shadow; grid 0.5 m",
            fontsize=7,
            color="0.3",
            bbox={"fc": "white", "ec": "none", "alpha": 0.8},
        )
        self.suptitle = self.fig.suptitle("", fontsize=9, y=0.99)
        self.drawn: list[np.ndarray] = []  # world joints (21, 3) per panel, last frame drawn

    def _update(self, t: int, fps: float) -> None:
        cx, cz = self.root[t, 0], self.root[t, 2]
        h = _VIEW_HALF
        xs = np.arange(np.ceil((cx - h) / _GRID_STEP), np.floor((cx + h) / _GRID_STEP) + 1)
        zs = np.arange(np.ceil((cz - h) / _GRID_STEP), np.floor((cz + h) / _GRID_STEP) + 1)
        grid = [((x, 0, cz - h), (x, 0, cz + h)) for x in xs * _GRID_STEP]
        grid += [((cx - h, 0, z), (cx + h, 0, z)) for z in zs * _GRID_STEP]
        self.drawn = []
        for panel, world, (low, prints) in zip(self.panels, self.worlds, self.marks, strict=True):
            ax, j = panel["ax"], world[t]
            ax.set_xlim(cx - h, cx + h)
            ax.set_ylim(0.0, _VIEW_HEIGHT)
            ax.set_zlim(cz - h, cz + h)
            ax.view_init(elev=_ELEVATION, azim=self.azimuths[t], vertical_axis="y")
            panel["grid"].set_segments(grid)
            panel["bones"].set_segments([j[[p, c]] for p, c in _BONES])
            shadow = j * np.array([1.0, 0.0, 1.0])
            panel["shadow"].set_segments([shadow[[p, c]] for p, c in _BONES])
            for f, line in enumerate(panel["prints"]):
                past = prints[: t + 1, f]
                line.set_data_3d(*_finite(past).T)
            panel["marks"].set_data_3d(*_finite(low[t]).T)
            self.drawn.append(j)
        self.suptitle.set_text(f"{self.title or ''}  t = {t / fps:.2f} s".strip())

    def frame(self, t: int, fps: float) -> np.ndarray:
        """Frame t as an RGB array (H, W, 3)."""
        self._update(t, fps)
        self.fig.canvas.draw()
        return np.asarray(self.fig.canvas.buffer_rgba())[..., :3].copy()


def _stage(pose, control, compare, title, labels, dpi, fps) -> tuple[_Stage, int]:
    pose, control = _check(pose, control)
    poses = [pose]
    if compare is not None:
        poses.append(_check(compare, control, "compare")[0])
    n = min(len(p) for p in poses)
    worlds = [world_joints(p[:n], control[:n]) for p in poses]
    root, yaw = (np.asarray(a) for a in integrate_root(control[:n]))
    if labels is None and compare is not None:
        labels = ("sample", "ground truth")
    return _Stage(worlds, root, yaw, fps, title=title, labels=labels, dpi=dpi), n


def animate(
    pose,
    control,
    path,
    *,
    fps: float = 20.0,
    title: str | None = None,
    compare=None,
    max_fps: float = 20.0,
    dpi: int = 100,
    labels: tuple[str, str] | None = None,
    still: str | os.PathLike | None = None,
    max_seconds: float | None = MAX_GIF_SECONDS,
) -> Path:
    """Write a GIF of pose (T, 63) metres walking the path of control (T, 3) in the world.

    One 3D panel following the root, 640 x 480 px at ``dpi`` 100 (see the module docstring
    for what is drawn). ``compare``: an optional second pose sequence (T', 63) in a second
    panel on the same path with the same camera (1024 x 480 px in all), e.g. the ground
    truth beside a sample; ``labels`` names the two panels (default "sample", "ground
    truth"). Frames are subsampled to at most ``max_fps``. ``still``: also write the middle
    frame there at dpi 200 (PNG, or PDF/SVG by suffix), as :func:`render_still` does.
    ``max_seconds``: draw only the first this many seconds, with a ``UserWarning`` (None:
    all; :data:`MAX_GIF_SECONDS` by default, see there). Each frame lasts 1 / fps (the GIF's
    whole centiseconds spread by :func:`gif_durations`).
    """
    from PIL import Image

    stage, n = _stage(pose, control, compare, title, labels, dpi, fps)
    step = max(1, int(np.ceil(fps / max_fps)))
    if max_seconds is not None and n > max_seconds * fps:
        warnings.warn(
            f"{Path(path).name} shows the first {max_seconds:g} s of {n / fps:g} s (GIF frames "
            "are held in memory until written); cut the motion into parts, or pass "
            "max_seconds=None to render.animate for all of it",
            UserWarning,
            stacklevel=2,
        )
        n = max(1, int(max_seconds * fps))
    times = range(0, n, step)
    # one palette from a few frames (drawn first), then nearest-colour mapping: 10x faster
    # than an adaptive palette per frame, a smaller file, and each frame is kept only as its
    # palette indices (1 byte a pixel, not 3 bytes of RGB)
    sampled = {t: stage.frame(t, fps) for t in times[:: max(1, len(times) // 8)]}
    palette = Image.fromarray(np.concatenate(list(sampled.values()))).quantize(64)
    frames = [
        Image.fromarray(sampled.pop(t) if t in sampled else stage.frame(t, fps)).quantize(
            palette=palette, dither=Image.Dither.NONE
        )
        for t in times
    ]
    out = Path(path)
    out.parent.mkdir(parents=True, exist_ok=True)
    frames[0].save(
        out,
        save_all=True,
        append_images=frames[1:],
        duration=gif_durations(len(frames), fps / step),
        loop=0,
        optimize=True,
    )
    if still is not None:
        _save_still(stage, n // 2, fps, still, dpi=200)
    return out


def gif_durations(frames: int, fps: float) -> list[int]:
    """Per-frame GIF delays (ms) for ``frames`` frames at ``fps``: GIF stores whole
    centiseconds, so frame k lasts round(100 (k + 1) / fps) - round(100 k / fps) cs and the
    clip lasts frames / fps to within 5 ms (30 fps: 30, 40, 30 ms ... not 30 ms each, 10 %
    fast). At 20 fps every frame is 50 ms."""
    edges = np.round(100.0 * np.arange(frames + 1) / fps).astype(np.int64)
    return [int(10 * d) for d in np.diff(edges)]


def _save_still(stage: _Stage, t: int, fps: float, path, dpi: int) -> Path:
    stage._update(t, fps)
    out = Path(path)
    out.parent.mkdir(parents=True, exist_ok=True)
    stage.fig.savefig(out, dpi=dpi)
    return out


def render_still(
    pose,
    control,
    path,
    *,
    frame: int | None = None,
    fps: float = 20.0,
    title: str | None = None,
    compare=None,
    labels: tuple[str, str] | None = None,
    dpi: int = 200,
) -> Path:
    """One frame of :func:`animate` (default the middle one) as an image for papers: PNG
    at ``dpi`` (200 -> 1280 x 960 px for one panel), or PDF/SVG by the file's suffix. The
    footprints drawn are those up to ``frame``."""
    stage, n = _stage(pose, control, compare, title, labels, 100, fps)
    t = n // 2 if frame is None else int(frame)
    if not 0 <= t < n:
        raise ValueError(f"frame {frame} out of range for a clip of {n} frames")
    return _save_still(stage, t, fps, path, dpi)


def frame_grid(
    pose, control, path, *, n: int = 6, fps: float = 20.0, title: str | None = None, dpi: int = 70
) -> Path:
    """A PNG with ``n`` evenly spaced side views plus the top-view trajectory."""
    pose, control = _check(pose, control)
    world = world_joints(pose, control)
    root = np.asarray(integrate_root(control)[0])
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
    """``<name>.gif``, its middle frame ``<name>.png`` (dpi 200) and ``<name>_controls.png``
    of a :class:`Clip` in ``out_dir``; keys ``"gif"``, ``"still"``, ``"controls"``."""
    out = Path(out_dir)
    name = clip.name.replace(os.sep, "_")
    gif = animate(
        clip.pose,
        clip.control,
        out / f"{name}.gif",
        fps=clip.fps,
        title=clip.name,
        compare=compare,
        still=out / f"{name}.png",
    )
    return {
        "gif": gif,
        "still": out / f"{name}.png",
        "controls": plot_controls(
            clip.control, out / f"{name}_controls.png", clip.fps, title=clip.name
        ),
    }


__all__ = [
    "animate",
    "frame_grid",
    "plot_controls",
    "render_clip",
    "render_still",
    "world_joints",
    "NUM_JOINTS",
]
