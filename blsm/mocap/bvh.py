"""Biovision Hierarchy (BVH) motion files: reading, forward kinematics and resampling.

A BVH file has a ``HIERARCHY`` section (a tree of ``ROOT`` / ``JOINT`` / ``End Site`` blocks, each
with an ``OFFSET`` from its parent and, for joints, ``CHANNELS`` in any order and any rotation
order) and a ``MOTION`` section (``Frames:``, ``Frame Time:`` and one line of channel values per
frame). Rotation channels are Euler angles in degrees, composed in the order they are listed
(``Zrotation Yrotation Xrotation`` is ``R = Rz Ry Rx``), the local transform of a joint is
``[R | offset]``, and position channels, where a joint has them, are added to its ``OFFSET`` (the
reading the CC_Base files of ``../shared/mocap/cmu`` need: their root has a rest-height OFFSET and
small position values; a file whose root OFFSET is zero reads the same either way).

Units are not part of the format: they are declared (``units="cm"``) or inferred from the size of the
skeleton (``units="auto"``: the candidate among m, cm, mm and inches that makes it closest to a
1.7 m tall person). Everything returned is converted to metres.

Every problem in a file is a :class:`BvhError` (a ``ValueError``) of one line,
``"<file>:<line>: <problem>"``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation, Slerp

UNITS: dict[str, float] = {"m": 1.0, "cm": 0.01, "mm": 0.001, "in": 0.0254}
_ROT = {"Xrotation": "X", "Yrotation": "Y", "Zrotation": "Z"}
_POS = {"Xposition": 0, "Yposition": 1, "Zposition": 2}
MAX_ABS = 1e6
"""Largest magnitude of a value (an offset or position in file units, an angle in degrees): beyond it
a number is garbage (10 km in cm; 2778 turns), and Euler angles lose all precision long before 1e30."""


class BvhError(ValueError):
    """A malformed or unusable BVH file; the message is ``"<file>:<line>: <problem>"``."""


@dataclass
class BvhSkeleton:
    """The ``HIERARCHY`` of a BVH file (offsets in metres).

    Attributes:
        names: joint names (End Sites excluded), parents first.
        parents: parent index per joint, -1 for the root.
        offsets: (J, 3) offset of each joint from its parent, in the parent's frame.
        channels: per joint, its channel names in file order.
        end_sites: joint index -> (3,) End Site offset.
        lines: 1-based line number of each joint's ``ROOT`` / ``JOINT`` declaration.
    """

    names: list[str]
    parents: list[int]
    offsets: np.ndarray
    channels: list[list[str]]
    end_sites: dict[int, np.ndarray] = field(default_factory=dict)
    lines: list[int] = field(default_factory=list)

    def index(self, name: str) -> int:
        return self.names.index(name)


@dataclass
class BvhMotion:
    """A BVH clip as local joint transforms (metres, rotation matrices).

    Attributes:
        path: the file it was read from.
        skeleton: its hierarchy.
        rotations: (T, J, 3, 3) local rotation of each joint (identity where it has no rotation
            channels).
        translations: (T, J, 3) local translation of each joint (its offset, or its position
            channels added to it where it has them), in metres.
        fps: frames per second (``1 / Frame Time``, or the resampled rate).
        units: the unit of the file ("m", "cm", "mm" or "in") and whether it was inferred.
        first_frame_line: 1-based line of the first frame in the file.
    """

    path: Path
    skeleton: BvhSkeleton
    rotations: np.ndarray
    translations: np.ndarray
    fps: float
    units: str
    units_inferred: bool
    first_frame_line: int

    @property
    def num_frames(self) -> int:
        return int(self.rotations.shape[0])

    def global_transforms(self) -> tuple[np.ndarray, np.ndarray]:
        """Forward kinematics.

        Returns:
            rotations: (T, J, 3, 3) world rotation of each joint's frame.
            positions: (T, J, 3) world position of each joint, metres.
        """
        return forward_kinematics(self.skeleton.parents, self.rotations, self.translations)


def forward_kinematics(
    parents: list[int], rotations: np.ndarray, translations: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """World rotations (T, J, 3, 3) and positions (T, J, 3) from local ``[R | t]`` (parents first)."""
    g_rot = np.empty_like(rotations)
    g_pos = np.empty_like(translations)
    for j, p in enumerate(parents):
        if p < 0:
            g_rot[:, j] = rotations[:, j]
            g_pos[:, j] = translations[:, j]
        else:
            g_rot[:, j] = g_rot[:, p] @ rotations[:, j]
            g_pos[:, j] = g_pos[:, p] + (g_rot[:, p] @ translations[:, j, :, None])[..., 0]
    return g_rot, g_pos


def _fail(path: Path, line: int, msg: str) -> BvhError:
    return BvhError(f"{path}:{line}: {msg}")


def _floats(path: Path, line: int, tokens: list[str], what: str) -> np.ndarray:
    try:
        v = np.array([float(t) for t in tokens])
    except ValueError:
        bad = next(t for t in tokens if not _is_float(t))
        raise _fail(path, line, f"{what}: {bad!r} is not a number") from None
    if not np.isfinite(v).all():
        raise _fail(path, line, f"{what}: non-finite value ({tokens[int(np.argmin(np.isfinite(v)))]})")
    if (np.abs(v) > MAX_ABS).any():
        big = tokens[int(np.argmax(np.abs(v)))]
        raise _fail(path, line, f"{what}: value {big} is out of range (|v| > {MAX_ABS:g})")
    return v


def _is_float(t: str) -> bool:
    try:
        float(t)
    except ValueError:
        return False
    return True


def _parse_hierarchy(path: Path, lines: list[str]) -> tuple[BvhSkeleton, int]:
    """Parse HIERARCHY; return the skeleton (offsets in file units) and the index of MOTION."""
    i = 0
    n = len(lines)

    def next_tokens() -> tuple[int, list[str]]:
        nonlocal i
        while i < n:
            toks = lines[i].split()
            i += 1
            if toks:
                return i, toks
        raise _fail(path, n, "unexpected end of file inside HIERARCHY")

    ln, toks = next_tokens()
    if toks != ["HIERARCHY"]:
        raise _fail(path, ln, f"expected 'HIERARCHY', found {' '.join(toks)[:40]!r}")
    names: list[str] = []
    parents: list[int] = []
    offsets: list[np.ndarray] = []
    channels: list[list[str]] = []
    decl_lines: list[int] = []
    end_sites: dict[int, np.ndarray] = {}
    stack: list[int] = []  # joint index per open block (-2 for an End Site)
    pending: tuple[str, int] | None = None  # a declared node waiting for its '{'
    while True:
        ln, toks = next_tokens()
        key = toks[0]
        if key in ("ROOT", "JOINT"):
            if key == "ROOT" and (names or stack):
                raise _fail(path, ln, "more than one ROOT (only single-skeleton files are supported)")
            if key == "JOINT" and not stack:
                raise _fail(path, ln, "JOINT outside of a ROOT block")
            if key == "JOINT" and stack[-1] == -2:
                raise _fail(path, ln, "JOINT inside an End Site")
            if len(toks) < 2:
                raise _fail(path, ln, f"{key} without a name")
            name = " ".join(toks[1:])
            if name in names:
                raise _fail(path, ln, f"duplicate joint name {name!r}")
            pending = (name, ln)
        elif key == "End":
            if toks != ["End", "Site"]:
                raise _fail(path, ln, f"unknown keyword {' '.join(toks)[:40]!r}")
            if not stack or stack[-1] == -2:
                raise _fail(path, ln, "End Site outside of a joint")
            pending = ("\0end", ln)
        elif key == "{":
            if pending is None:
                raise _fail(path, ln, "'{' without a ROOT, JOINT or End Site before it")
            name, dl = pending
            pending = None
            if name == "\0end":
                stack.append(-2)
                end_sites[stack[-2]] = np.full(3, np.nan)
            else:
                names.append(name)
                parents.append(stack[-1] if stack else -1)
                offsets.append(np.full(3, np.nan))
                channels.append([])
                decl_lines.append(dl)
                stack.append(len(names) - 1)
        elif key == "}":
            if not stack:
                raise _fail(path, ln, "unbalanced '}'")
            j = stack.pop()
            where = "End Site" if j == -2 else f"joint {names[j]!r}"
            node_off = end_sites[stack[-1]] if j == -2 else offsets[j]
            if np.isnan(node_off).any():
                raise _fail(path, ln, f"{where} has no OFFSET")
            if not stack:
                break
        elif key == "OFFSET":
            if not stack or pending is not None:
                raise _fail(path, ln, "OFFSET outside of a block")
            if len(toks) != 4:
                raise _fail(path, ln, f"OFFSET needs 3 numbers, got {len(toks) - 1}")
            v = _floats(path, ln, toks[1:], "OFFSET")
            if stack[-1] == -2:
                end_sites[stack[-2]] = v
            else:
                offsets[stack[-1]] = v
        elif key == "CHANNELS":
            if not stack or stack[-1] == -2:
                raise _fail(path, ln, "CHANNELS outside of a joint")
            try:
                count = int(toks[1])
            except (IndexError, ValueError):
                raise _fail(path, ln, "CHANNELS needs a count") from None
            chans = toks[2:]
            if len(chans) != count:
                raise _fail(path, ln, f"CHANNELS says {count} but lists {len(chans)}")
            for c in chans:
                if c not in _ROT and c not in _POS:
                    raise _fail(path, ln, f"unknown channel {c!r}")
            if len(set(chans)) != len(chans):
                raise _fail(path, ln, "repeated channel")
            channels[stack[-1]] = chans
        elif key == "MOTION":
            raise _fail(path, ln, "MOTION before the hierarchy was closed (unbalanced braces)")
        else:
            raise _fail(path, ln, f"unknown keyword {key[:40]!r} in HIERARCHY")
    skel = BvhSkeleton(
        names=names,
        parents=parents,
        offsets=np.stack(offsets),
        channels=channels,
        end_sites=end_sites,
        lines=decl_lines,
    )
    return skel, i


def infer_units(skeleton: BvhSkeleton) -> str:
    """The unit that makes the skeleton's rest-pose extent closest to a 1.7 m person."""
    rot = np.broadcast_to(np.eye(3), (1, len(skeleton.names), 3, 3))
    _, pos = forward_kinematics(skeleton.parents, rot, skeleton.offsets[None])
    pts = [pos[0]]
    for j, off in skeleton.end_sites.items():
        pts.append((pos[0, j] + off)[None])
    allp = np.concatenate(pts)
    extent = float((allp.max(0) - allp.min(0)).max())
    if extent <= 0:
        return "m"
    return min(UNITS, key=lambda u: abs(math.log(extent * UNITS[u] / 1.7)))


def read_bvh(path: str | Path, units: str = "auto", fps: float | None = None) -> BvhMotion:
    """Read a BVH file into local transforms in metres.

    Args:
        path: the ``.bvh`` file.
        units: "auto" (inferred from the skeleton's size) or one of "m", "cm", "mm", "in".
        fps: resample to this frame rate (see :func:`resample`); None keeps the file's rate.

    Returns:
        :class:`BvhMotion`.

    Raises:
        BvhError: ``"<file>:<line>: <problem>"`` for anything malformed: an unknown keyword,
            unbalanced braces, a missing OFFSET, channel count or names, a missing ``Frames:`` or
            ``Frame Time:``, a frame with too few or too many values, a value that is not a finite
            number or is larger than ``MAX_ABS``, fewer frame lines than ``Frames:`` announces.
    """
    path = Path(path)
    if units != "auto" and units not in UNITS:
        raise ValueError(f"units must be 'auto' or one of {sorted(UNITS)}, got {units!r}")
    lines = _read_lines(path)
    skel, i = _parse_hierarchy(path, lines)
    n_frames, frame_time, i = _parse_motion_header(path, lines, i)
    data, first = _parse_frames(path, lines, i, n_frames, sum(len(c) for c in skel.channels))
    unit = infer_units(skel) if units == "auto" else units
    scale = UNITS[unit]
    skel = replace(
        skel,
        offsets=skel.offsets * scale,
        end_sites={j: o * scale for j, o in skel.end_sites.items()},
    )
    rot, trans = _local_transforms(skel, data, scale)
    motion = BvhMotion(
        path=path,
        skeleton=skel,
        rotations=rot,
        translations=trans,
        fps=1.0 / frame_time,
        units=unit,
        units_inferred=units == "auto",
        first_frame_line=first,
    )
    return motion if fps is None else resample(motion, fps)


def _read_lines(path: Path) -> list[str]:
    """The file's lines; an unreadable or non-UTF-8 file is a :class:`BvhError`."""
    try:
        text = path.read_text(encoding="utf-8-sig", errors="strict")  # a leading BOM is not content
    except OSError as exc:
        raise BvhError(f"{path}:0: cannot read ({exc.strerror})") from None
    except UnicodeDecodeError as exc:
        line = path.read_bytes()[: exc.start].count(b"\n") + 1
        raise BvhError(f"{path}:{line}: not a text file (invalid UTF-8)") from None
    return text.splitlines()


def _parse_motion_header(path: Path, lines: list[str], i: int) -> tuple[int, float, int]:
    """``MOTION``, ``Frames:`` and ``Frame Time:`` from line index ``i``.

    Returns:
        (number of frames, seconds per frame, index of the first frame line).
    """

    def header(key: str) -> tuple[int, str]:
        nonlocal i
        while i < len(lines) and not lines[i].strip():
            i += 1
        if i >= len(lines):
            raise _fail(path, len(lines), f"missing {key!r} (file ends)")
        s = lines[i].strip()
        i += 1
        if not s.startswith(key):
            raise _fail(path, i, f"expected {key!r}, found {s[:40]!r}")
        return i, s[len(key) :].strip()

    header("MOTION")
    ln, v = header("Frames:")
    try:
        n_frames = int(v)
    except ValueError:
        raise _fail(path, ln, f"Frames: {v!r} is not an integer") from None
    if n_frames < 1:
        raise _fail(path, ln, f"Frames: must be at least 1, got {n_frames}")
    ln, v = header("Frame Time:")
    try:
        frame_time = float(v)
    except ValueError:
        raise _fail(path, ln, f"Frame Time: {v!r} is not a number") from None
    if not (math.isfinite(frame_time) and frame_time > 0):
        raise _fail(path, ln, f"Frame Time: must be positive, got {v}")
    return n_frames, frame_time, i


def _parse_frames(path: Path, lines: list[str], i: int, n_frames: int, n_chan: int) -> tuple[np.ndarray, int]:
    """The frame block from line index ``i``: exactly ``n_frames`` lines of ``n_chan`` finite values
    (trailing blank lines are allowed, blank or missing lines inside the block are not).

    Returns:
        (values (n_frames, n_chan) float64, 1-based line number of the first frame).
    """
    first = i + 1
    rows = lines[i : i + n_frames]
    if len(rows) < n_frames or any(not r.strip() for r in rows):
        k = next((k for k, r in enumerate(rows) if not r.strip()), len(rows))
        raise _fail(
            path,
            first + k,
            f"truncated motion: Frames: says {n_frames} but frame {k + 1} is missing",
        )
    extra = [k for k, r in enumerate(lines[i + n_frames :]) if r.strip()]
    if extra:
        raise _fail(
            path,
            first + n_frames + extra[0],
            f"more frame lines than Frames: {n_frames} announces",
        )
    tokens = [r.split() for r in rows]
    for k, t in enumerate(tokens):
        if len(t) != n_chan:
            raise _fail(
                path,
                first + k,
                f"frame {k + 1} has {len(t)} values, the hierarchy declares {n_chan} channels",
            )
    try:
        data = np.array(tokens, dtype=np.float64)
    except ValueError:
        for k, t in enumerate(tokens):
            _floats(path, first + k, t, f"frame {k + 1}")
        raise  # pragma: no cover - _floats raises first
    bad = ~np.isfinite(data)
    if bad.any():
        k, c = np.argwhere(bad)[0]
        raise _fail(path, first + int(k), f"frame {k + 1}: non-finite value in channel {c + 1}")
    huge = np.abs(data) > MAX_ABS
    if huge.any():
        k, c = np.argwhere(huge)[0]
        msg = f"frame {k + 1}: value {data[k, c]:g} in channel {c + 1} is out of range (|v| > {MAX_ABS:g})"
        raise _fail(path, first + int(k), msg)
    return data, first


def _local_transforms(skel: BvhSkeleton, data: np.ndarray, scale: float) -> tuple[np.ndarray, np.ndarray]:
    """Local rotations (T, J, 3, 3) and translations (T, J, 3) in metres of the frame values (T, C);
    ``skel`` has its offsets in metres already, ``scale`` converts the position channels."""
    n_frames, n_j = len(data), len(skel.names)
    rot = np.broadcast_to(np.eye(3), (n_frames, n_j, 3, 3)).copy()
    trans = np.broadcast_to(skel.offsets, (n_frames, n_j, 3)).copy()
    col = 0
    for j, chans in enumerate(skel.channels):
        order = "".join(_ROT[c] for c in chans if c in _ROT)
        rot_cols = [col + k for k, c in enumerate(chans) if c in _ROT]
        for k, c in enumerate(chans):
            if c in _POS:
                trans[:, j, _POS[c]] += data[:, col + k] * scale
        if order:
            # Upper-case sequence = intrinsic rotations, composed in listed order (R = R1 R2 R3).
            rot[:, j] = Rotation.from_euler(order, data[:, rot_cols], degrees=True).as_matrix()
        col += len(chans)
    return rot, trans


def resample(motion: BvhMotion, fps: float) -> BvhMotion:
    """Resample a clip to ``fps``: rotations by slerp, translations linearly.

    The new frames are at ``t = k / fps`` for every k with ``t`` inside the clip's duration.
    """
    if not (math.isfinite(fps) and fps > 0):
        raise ValueError(f"fps must be positive, got {fps}")
    t_src = np.arange(motion.num_frames) / motion.fps
    last = t_src[-1] * fps
    # Frame Time is written rounded (0.016667 for 1/60): snap to the closer frame count.
    n_new = int(math.floor(last + 0.01 + 1e-4 * last)) + 1
    t_new = np.minimum(np.arange(n_new) / fps, t_src[-1])
    if motion.num_frames == 1 or abs(fps - motion.fps) < 1e-9:
        return replace(motion, fps=float(fps)) if motion.num_frames == 1 else motion
    n_j = motion.rotations.shape[1]
    rot = np.empty((n_new, n_j, 3, 3))
    for j in range(n_j):
        rot[:, j] = Slerp(t_src, Rotation.from_matrix(motion.rotations[:, j]))(t_new).as_matrix()
    trans = np.empty((n_new, n_j, 3))
    for j in range(n_j):
        for c in range(3):
            trans[:, j, c] = np.interp(t_new, t_src, motion.translations[:, j, c])
    return replace(motion, rotations=rot, translations=trans, fps=float(fps))
