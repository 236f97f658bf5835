"""BVH reader and vectorised forward kinematics (own numpy code).

A BVH file has a ``HIERARCHY`` section (``ROOT``/``JOINT``/``End Site`` blocks with an
``OFFSET`` and, for joints, ``CHANNELS n name...``) and a ``MOTION`` section
(``Frames: F``, ``Frame Time: dt`` and F lines of channel values).

Conventions used by :func:`forward_kinematics` (the usual ones, as in Blender and bvhio):

* Rotation channels are in degrees and compose in the order they are listed: for channels
  ``Zrotation Xrotation Yrotation`` the joint's local rotation is ``R = Rz @ Rx @ Ry``
  (column vectors, child-to-parent).
* A joint's local translation is its ``OFFSET``; if the joint has position channels their
  values *replace* the corresponding offset components (for a root they are the global
  position; on Bandai's other joints they equal the offset).
* World transforms: ``R_w[j] = R_w[parent] @ R[j]`` and
  ``p_w[j] = p_w[parent] + R_w[parent] @ t[j]``.

Any malformed input raises :class:`motionflows.errors.MotionDataError` naming the file,
the line and the problem; nothing is returned partially.
"""

from __future__ import annotations

import dataclasses
import math
import os
from pathlib import Path

import numpy as np

from motionflows.errors import MotionDataError

_POS = ("Xposition", "Yposition", "Zposition")
_ROT = ("Xrotation", "Yrotation", "Zrotation")
VALID_CHANNELS = _POS + _ROT

MIN_FRAME_TIME_S = 1e-4
"""Shortest accepted ``Frame Time`` (10 000 fps)."""
MAX_FRAME_TIME_S = 10.0
"""Longest accepted ``Frame Time`` (one frame per 10 s)."""
MAX_ROTATION_DEG = 1e5
"""Largest accepted |rotation channel| in degrees (~280 turns; unwrapped angles fit)."""
MAX_LENGTH_VALUE = 1e9
"""Largest accepted |offset| or |position channel| in file units, before any unit scale
(the 1 km limit on positions in metres is applied after conversion, in ``features``)."""


@dataclasses.dataclass(frozen=True)
class BVH:
    """A parsed BVH file.

    Attributes:
      names: (J,) joint names in file order (End Sites excluded).
      parents: (J,) parent index per joint (-1 for the root).
      offsets: (J, 3) float64 joint offsets in file units.
      channels: per joint, the tuple of channel names (possibly empty).
      channel_start: (J,) index of each joint's first channel in a motion row.
      end_sites: tuple of (parent joint index, (3,) offset) per End Site.
      motion: (F, C) float64 channel values.
      frame_time: seconds per frame.
      path: where the data came from (for messages).
    """

    names: tuple[str, ...]
    parents: tuple[int, ...]
    offsets: np.ndarray
    channels: tuple[tuple[str, ...], ...]
    channel_start: tuple[int, ...]
    end_sites: tuple[tuple[int, np.ndarray], ...]
    motion: np.ndarray
    frame_time: float
    path: str = "<string>"

    @property
    def num_frames(self) -> int:
        return int(self.motion.shape[0])

    @property
    def fps(self) -> float:
        return 1.0 / self.frame_time

    def index(self, name: str) -> int:
        try:
            return self.names.index(name)
        except ValueError:
            raise MotionDataError(
                f"joint {name!r} is not in the file (joints: {', '.join(self.names)}); "
                "use a skeleton mapping that matches this file",
                path=self.path,
            ) from None


def _err(msg: str, path: str, line: int | None) -> MotionDataError:
    return MotionDataError(msg, path=path, line=line)


def read_bvh(path: str | os.PathLike) -> BVH:
    """Parse a BVH file from disk (see :func:`parse_bvh`)."""
    p = Path(path)
    try:
        text = p.read_text(encoding="utf-8-sig", errors="replace")
    except FileNotFoundError:
        raise MotionDataError("file not found; check the path", path=str(p)) from None
    except OSError as err:
        raise MotionDataError(f"cannot read the file ({err})", path=str(p)) from None
    return parse_bvh(text, path=str(p))


def _hierarchy_tokens(lines: list[str], path: str) -> tuple[list[tuple[str, int]], int]:
    """Split the lines before ``MOTION`` into (token, 1-based line) pairs (braces are tokens
    of their own); return them with the 0-based index of the ``MOTION`` line."""
    tokens: list[tuple[str, int]] = []
    motion_line = None
    for i, line in enumerate(lines):
        stripped = line.strip()
        if stripped.upper().startswith("MOTION"):
            motion_line = i
            break
        for tok in stripped.replace("{", " { ").replace("}", " } ").split():
            tokens.append((tok, i + 1))
    if not tokens or tokens[0][0].upper() != "HIERARCHY":
        line = tokens[0][1] if tokens else 1
        raise _err("missing HIERARCHY section (a BVH file starts with HIERARCHY)", path, line)
    if motion_line is None:
        raise _err(
            "missing MOTION section after the hierarchy (the file may be truncated)",
            path,
            len(lines),
        )
    return tokens, motion_line


class _JointTree:
    """Recursive-descent parser of the hierarchy tokens (after ``HIERARCHY``).

    Fills, in file order: ``names``, ``parents`` (-1 for the root), ``offsets`` ((3,) per
    joint), ``channels`` (a tuple of names per joint) and ``end_sites`` ((parent, (3,))).
    Use :meth:`root`, then ``joint(-1, False)``, then :meth:`check_complete`.
    """

    def __init__(self, tokens: list[tuple[str, int]], path: str):
        self.tokens = tokens
        self.path = path
        self.pos = 1  # tokens[0] is HIERARCHY
        self.names: list[str] = []
        self.parents: list[int] = []
        self.offsets: list[np.ndarray] = []
        self.channels: list[tuple[str, ...]] = []
        self.end_sites: list[tuple[int, np.ndarray]] = []

    def take(self, expected: str | None = None) -> tuple[str, int]:
        """Consume the next (token, line); raise if none is left or it is not ``expected``."""
        if self.pos >= len(self.tokens):
            last = self.tokens[-1][1] if self.tokens else 1
            want = f" (expected {expected!r})" if expected else ""
            raise _err(f"hierarchy ends unexpectedly{want}", self.path, last)
        tok, ln = self.tokens[self.pos]
        self.pos += 1
        if expected is not None and tok.upper() != expected.upper():
            raise _err(f"expected {expected!r} but found {tok!r}", self.path, ln)
        return tok, ln

    def number(self) -> float:
        """Consume one finite offset value, at most ``MAX_LENGTH_VALUE`` in size."""
        tok, ln = self.take()
        try:
            value = float(tok)
        except ValueError:
            raise _err(f"expected a number but found {tok!r}", self.path, ln) from None
        if not math.isfinite(value):
            raise _err(f"non-finite value {tok!r} in the hierarchy", self.path, ln)
        if abs(value) > MAX_LENGTH_VALUE:
            raise _err(
                f"offset {tok} is beyond the limit of {MAX_LENGTH_VALUE:g} file units; "
                "check the file's units",
                self.path,
                ln,
            )
        return value

    def offset(self) -> np.ndarray:
        """Consume ``OFFSET x y z`` into a (3,) float64 array."""
        self.take("OFFSET")
        return np.array([self.number(), self.number(), self.number()], dtype=np.float64)

    def channel_list(self) -> tuple[str, ...]:
        """Consume an optional ``CHANNELS n name...`` (0 <= n <= 6 distinct valid names)."""
        tok = self.tokens[self.pos][0] if self.pos < len(self.tokens) else ""
        if tok.upper() != "CHANNELS":
            return ()
        self.take()
        count_tok, cln = self.take()
        try:
            count = int(count_tok)
        except ValueError:
            raise _err(f"CHANNELS count {count_tok!r} is not an integer", self.path, cln) from None
        if count < 0 or count > 6:
            raise _err(f"CHANNELS count {count} must be between 0 and 6", self.path, cln)
        got = []
        for _ in range(count):
            ctok, cl = self.take()
            if ctok not in VALID_CHANNELS:
                raise _err(
                    f"unknown channel name {ctok!r}; valid: {', '.join(VALID_CHANNELS)}",
                    self.path,
                    cl,
                )
            got.append(ctok)
        if len(set(got)) != len(got):
            raise _err(f"repeated channel in {' '.join(got)}", self.path, cln)
        return tuple(got)

    def root(self) -> None:
        """Consume ``ROOT name`` and record the root joint (its block follows)."""
        tok, ln = self.take()
        if tok.upper() != "ROOT":
            raise _err(f"expected ROOT after HIERARCHY but found {tok!r}", self.path, ln)
        root_name, _ = self.take()
        self.names.append(root_name)
        self.parents.append(-1)

    def joint(self, parent: int, is_end: bool) -> None:
        """Consume one ``{ ... }`` block: an End Site of ``parent``, or else the joint whose
        name was just recorded, with its offset, channels and child blocks."""
        self.take("{")
        offset = self.offset()
        if is_end:
            self.end_sites.append((parent, offset))
            self.take("}")
            return
        index = len(self.names) - 1  # the caller recorded this joint's name
        self.offsets.append(offset)
        self.channels.append(self.channel_list())
        while True:
            tok, ln = self.take()
            key = tok.upper()
            if key == "}":
                return
            if key == "JOINT":
                name, _ = self.take()
                self.names.append(name)
                self.parents.append(index)
                self.joint(index, False)
            elif key == "END":
                self.take("Site")
                self.joint(index, True)
            else:
                raise _err(f"unexpected {tok!r} inside joint {self.names[index]!r}", self.path, ln)

    def check_complete(self) -> None:
        """Raise on tokens after the root block or on a joint name used twice."""
        if self.pos < len(self.tokens):
            tok, ln = self.tokens[self.pos]
            raise _err(
                f"unexpected {tok!r} after the root joint (only one ROOT is supported)",
                self.path,
                ln,
            )
        names = self.names
        if len(set(names)) != len(names):
            seen: set[str] = set()
            dup = next(n for n in names if n in seen or seen.add(n))
            line = [ln for k, (tok, ln) in enumerate(self.tokens) if tok == dup and k > 0][-1]
            raise _err(
                f"joint name {dup!r} is used by more than one joint; rename one of them",
                self.path,
                line,
            )


def _header_value(lines: list[str], i: int, label: str, path: str) -> tuple[str, int]:
    """The text after ``label:`` on the first non-blank line from index ``i`` on, and that
    line's 1-based number (which is also the index of the line after it)."""
    while i < len(lines) and not lines[i].strip():
        i += 1
    if i >= len(lines):
        raise _err(f"missing '{label}:' line in MOTION", path, len(lines))
    line = lines[i].strip()
    if not line.lower().replace(" ", "").startswith(label.lower().replace(" ", "") + ":"):
        raise _err(f"expected '{label}:' but found {line[:40]!r}", path, i + 1)
    return line.split(":", 1)[1].strip(), i + 1


def _motion_header(lines: list[str], motion_line: int, path: str) -> tuple[int, float, int]:
    """Parse ``Frames: F`` and ``Frame Time: dt`` after the MOTION line (0-based index
    ``motion_line``): (F >= 1, dt in seconds within the accepted range, index of the line
    after the header)."""
    frames_txt, frames_ln = _header_value(lines, motion_line + 1, "Frames", path)
    try:
        n_frames = int(frames_txt)
    except ValueError:
        raise _err(f"Frames count {frames_txt!r} is not an integer", path, frames_ln) from None
    if n_frames < 1:
        raise _err(f"Frames is {n_frames}; a motion needs at least one frame", path, frames_ln)
    ft_txt, ft_ln = _header_value(lines, frames_ln, "Frame Time", path)
    try:
        frame_time = float(ft_txt)
    except ValueError:
        raise _err(f"Frame Time {ft_txt!r} is not a number", path, ft_ln) from None
    if not (math.isfinite(frame_time) and frame_time > 0):
        raise _err(f"Frame Time must be a positive number, got {ft_txt!r}", path, ft_ln)
    if not MIN_FRAME_TIME_S <= frame_time <= MAX_FRAME_TIME_S:
        raise _err(
            f"Frame Time {ft_txt} s is outside the accepted range {MIN_FRAME_TIME_S:g} .. "
            f"{MAX_FRAME_TIME_S:g} s ({1 / MAX_FRAME_TIME_S:g} .. {1 / MIN_FRAME_TIME_S:g} "
            "fps); fix the header (Frame Time is seconds per frame, e.g. 0.0333333 for 30 fps)",
            path,
            ft_ln,
        )
    return n_frames, frame_time, ft_ln


def _frame_lines(
    lines: list[str], start: int, n_frames: int, path: str
) -> tuple[list[str], list[int]]:
    """The non-blank lines from index ``start`` on and their 1-based numbers; raise unless
    there are exactly ``n_frames`` of them."""
    data_lines = []
    line_numbers = []
    for j in range(start, len(lines)):
        if lines[j].strip():
            data_lines.append(lines[j])
            line_numbers.append(j + 1)
    if len(data_lines) < n_frames:
        raise _err(
            f"truncated motion: Frames says {n_frames} but only {len(data_lines)} frame lines "
            "follow; re-export or re-download the file",
            path,
            len(lines),
        )
    if len(data_lines) > n_frames:
        raise _err(
            f"Frames says {n_frames} but {len(data_lines)} frame lines follow; fix the "
            "Frames count",
            path,
            line_numbers[n_frames],
        )
    return data_lines, line_numbers


def _frame_values(
    data_lines: list[str], line_numbers: list[int], n_chan: int, path: str
) -> np.ndarray:
    """(F, C) float64 values of the F frame lines; raise on a line without exactly
    ``n_chan`` values or on a non-numeric or non-finite value."""
    split = [ln.split() for ln in data_lines]
    counts = np.fromiter((len(s) for s in split), dtype=np.int64, count=len(split))
    bad = np.flatnonzero(counts != n_chan)
    if bad.size:
        k = int(bad[0])
        raise _err(
            f"frame {k} has {counts[k]} values but the hierarchy declares {n_chan} channels",
            path,
            line_numbers[k],
        )
    try:
        motion = np.array([v for s in split for v in s], dtype=np.float64)
    except ValueError:
        for k, s in enumerate(split):
            for v in s:
                try:
                    float(v)
                except ValueError:
                    raise _err(
                        f"non-numeric value {v!r} in frame {k}", path, line_numbers[k]
                    ) from None
        raise  # pragma: no cover
    motion = motion.reshape(len(split), n_chan)
    finite = np.isfinite(motion)
    if not finite.all():
        k = int(np.flatnonzero(~finite.all(axis=1))[0])
        raise _err(f"non-finite value in frame {k}", path, line_numbers[k])
    return motion


def _check_channel_limits(
    motion: np.ndarray,
    names: list[str],
    channels: list[tuple[str, ...]],
    line_numbers: list[int],
    path: str,
) -> None:
    """Raise on the first value of (F, C) ``motion`` beyond ``MAX_ROTATION_DEG`` (rotation
    channels) or ``MAX_LENGTH_VALUE`` (position channels), naming joint, channel and frame."""
    flat = [(j, ch) for j, chans in enumerate(channels) for ch in chans]
    for limit, kind, unit in (
        (MAX_ROTATION_DEG, _ROT, "degrees"),
        (MAX_LENGTH_VALUE, _POS, "file units"),
    ):
        cols = [c for c, (_, ch) in enumerate(flat) if ch in kind]
        if not cols:
            continue
        over = np.abs(motion[:, cols]) > limit
        if over.any():
            k, c = (int(v[0]) for v in np.nonzero(over))
            j, ch = flat[cols[c]]
            raise _err(
                f"{ch} of joint {names[j]!r} is {motion[k, cols[c]]:g} {unit} in frame {k}, "
                f"beyond the limit of {limit:g}; the file is damaged or uses other units",
                path,
                line_numbers[k],
            )


def parse_bvh(text: str, *, path: str = "<string>") -> BVH:
    """Parse BVH text into a :class:`BVH`; raise ``MotionDataError`` on any problem."""
    lines = text.splitlines()
    if not any(line.strip() for line in lines):
        raise _err("the file is empty; expected a BVH file starting with HIERARCHY", path, 1)
    tokens, motion_line = _hierarchy_tokens(lines, path)
    tree = _JointTree(tokens, path)
    tree.root()
    tree.joint(-1, False)
    tree.check_complete()

    n_frames, frame_time, start = _motion_header(lines, motion_line, path)
    data_lines, line_numbers = _frame_lines(lines, start, n_frames, path)
    n_chan = sum(len(c) for c in tree.channels)
    motion = _frame_values(data_lines, line_numbers, n_chan, path)
    _check_channel_limits(motion, tree.names, tree.channels, line_numbers, path)

    starts = np.cumsum([0] + [len(c) for c in tree.channels])[:-1]
    return BVH(
        names=tuple(tree.names),
        parents=tuple(tree.parents),
        offsets=np.stack(tree.offsets),
        channels=tuple(tree.channels),
        channel_start=tuple(int(s) for s in starts),
        end_sites=tuple(tree.end_sites),
        motion=motion,
        frame_time=frame_time,
        path=path,
    )


def _axis_rotation(axis: str, angle_rad: np.ndarray) -> np.ndarray:
    """(F, 3, 3) rotation matrices about one axis (right-handed, column vectors)."""
    c, s = np.cos(angle_rad), np.sin(angle_rad)
    one, zero = np.ones_like(c), np.zeros_like(c)
    if axis == "X":
        rows = [[one, zero, zero], [zero, c, -s], [zero, s, c]]
    elif axis == "Y":
        rows = [[c, zero, s], [zero, one, zero], [-s, zero, c]]
    else:
        rows = [[c, -s, zero], [s, c, zero], [zero, zero, one]]
    return np.stack([np.stack(r, axis=-1) for r in rows], axis=-2)


def local_transforms(bvh: BVH) -> tuple[np.ndarray, np.ndarray]:
    """Per-frame local rotations (F, J, 3, 3) and translations (F, J, 3)."""
    f = bvh.num_frames
    n = len(bvh.names)
    rot = np.broadcast_to(np.eye(3), (f, n, 3, 3)).copy()
    trans = np.broadcast_to(bvh.offsets, (f, n, 3)).copy()
    for j, chans in enumerate(bvh.channels):
        start = bvh.channel_start[j]
        for k, ch in enumerate(chans):
            values = bvh.motion[:, start + k]
            if ch in _POS:
                trans[:, j, _POS.index(ch)] = values
            else:
                rot[:, j] = rot[:, j] @ _axis_rotation(ch[0], np.deg2rad(values))
    return rot, trans


def forward_kinematics(
    bvh: BVH, *, return_rotations: bool = False
) -> np.ndarray | tuple[np.ndarray, np.ndarray]:
    """World joint positions (F, J, 3) in file units; with ``return_rotations`` the pair
    (positions, world rotations (F, J, 3, 3)).

    ``R_w[j] = R_w[parent] @ R_local[j]``, ``p_w[j] = p_w[parent] + R_w[parent] @ t[j]``;
    vectorised over frames, one pass over joints in file order (parents come first).
    """
    rot, trans = local_transforms(bvh)
    world_r = np.empty_like(rot)
    world_p = np.empty_like(trans)
    for j, parent in enumerate(bvh.parents):
        if parent < 0:
            world_r[:, j] = rot[:, j]
            world_p[:, j] = trans[:, j]
        else:
            world_r[:, j] = world_r[:, parent] @ rot[:, j]
            world_p[:, j] = world_p[:, parent] + np.einsum(
                "fab,fb->fa", world_r[:, parent], trans[:, j]
            )
    return (world_p, world_r) if return_rotations else world_p
