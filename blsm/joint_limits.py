"""Joint-limited single-axis pose atoms (paper 000 Sec. 3.1, Eq. 6; thesis Eq. 5.6).

Each of the 47 pose atoms ("degrees of freedom", DoFs) is a rotation about one signed axis of one
joint's bind frame, with an anatomical range ``[theta_min, theta_max]`` in radians. An
unconstrained value ``x`` is mapped into the range by Eq. 6::

    theta = (theta_max - theta_min) / 2 * tanh(x) + (theta_min + theta_max) / 2

The table of atoms (names, joints, axes, limits, left/right mirror pairs and their sign flips) lives
in one file, ``blsm/data/dofs.yaml``; :func:`load_dof_table` reads and validates it.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import torch
import yaml

DEFAULT_DOF_TABLE = Path(__file__).parent / "data" / "dofs.yaml"

_AXES = {"x": 0, "y": 1, "z": 2}


@dataclass(frozen=True)
class Dof:
    """One pose atom.

    Attributes:
        name: ``"<joint>.<motion>"``, e.g. ``"knee_l.flex"``.
        joint: name of the bone whose head is the rotating joint.
        axis: 0, 1 or 2 for the x, y or z axis of the joint's bind frame.
        axis_sign: +1 or -1; a positive angle rotates by ``+theta`` about ``axis_sign * e_axis``.
        limits: ``(theta_min, theta_max)`` in radians, ``theta_min <= 0 <= theta_max``.
        mirror: name of the atom that mirrors this one across the sagittal (x = 0) plane.
        mirror_sign: +1 or -1, ``theta_mirror = mirror_sign * theta``.
    """

    name: str
    joint: str
    axis: int
    axis_sign: int
    limits: tuple[float, float]
    mirror: str
    mirror_sign: int


@dataclass(frozen=True)
class DofTable:
    """The validated table of pose atoms, in a fixed order (the order of the 47-D pose vector)."""

    dofs: tuple[Dof, ...]
    source: str  # the YAML text it was read from, stored verbatim in model files

    @property
    def names(self) -> list[str]:
        return [d.name for d in self.dofs]

    def __len__(self) -> int:
        return len(self.dofs)

    def limits_tensor(self) -> torch.Tensor:
        """(D, 2) float64 tensor of ``[theta_min, theta_max]`` in radians."""
        return torch.tensor([d.limits for d in self.dofs], dtype=torch.float64)

    def mirror_permutation(self) -> tuple[list[int], list[int]]:
        """Permutation and signs such that ``mirrored[:, i] = sign[i] * theta[:, perm[i]]``."""
        index = {d.name: i for i, d in enumerate(self.dofs)}
        perm = [index[d.mirror] for d in self.dofs]
        sign = [d.mirror_sign for d in self.dofs]
        return perm, sign


def parse_dof_table(text: str, source_name: str = "<string>") -> DofTable:
    """Parse and validate the YAML DoF table.

    Args:
        text: YAML text with keys ``units`` (``degrees`` or ``radians``) and ``dofs`` (a list of
            mappings with keys name, joint, axis, min, max, mirror, mirror_sign).
        source_name: file name used in error messages.

    Returns:
        The validated :class:`DofTable`.

    Raises:
        ValueError: naming the file and the problem.
    """
    try:
        raw = yaml.safe_load(text)
    except yaml.YAMLError as exc:
        raise ValueError(f"{source_name}: not valid YAML ({exc})") from exc
    if not isinstance(raw, dict) or set(raw) - {"units", "dofs"} or "dofs" not in raw:
        raise ValueError(f"{source_name}: expected top-level keys 'units' and 'dofs'")
    units = raw.get("units", "degrees")
    if units not in ("degrees", "radians"):
        raise ValueError(f"{source_name}: units must be 'degrees' or 'radians', got {units!r}")
    scale = math.pi / 180.0 if units == "degrees" else 1.0
    keys = {"name", "joint", "axis", "min", "max", "mirror", "mirror_sign"}
    dofs = []
    for i, entry in enumerate(raw["dofs"]):
        if not isinstance(entry, dict) or set(entry) != keys:
            raise ValueError(f"{source_name}: dof #{i} must have exactly the keys {sorted(keys)}")
        axis = str(entry["axis"])
        sign = -1 if axis.startswith("-") else 1
        letter = axis.lstrip("+-")
        if letter not in _AXES:
            raise ValueError(f"{source_name}: dof {entry['name']!r} has unknown axis {axis!r}")
        lo, hi = float(entry["min"]) * scale, float(entry["max"]) * scale
        if not lo <= 0.0 <= hi or lo == hi:
            raise ValueError(
                f"{source_name}: dof {entry['name']!r} limits [{entry['min']}, {entry['max']}] "
                "must contain 0 and be non-empty"
            )
        if entry["mirror_sign"] not in (1, -1):
            raise ValueError(f"{source_name}: dof {entry['name']!r} mirror_sign must be 1 or -1")
        if not str(entry["name"]).startswith(str(entry["joint"]) + "."):
            raise ValueError(f"{source_name}: dof {entry['name']!r} must be named '<joint>.<motion>'")
        dofs.append(
            Dof(
                name=str(entry["name"]),
                joint=str(entry["joint"]),
                axis=_AXES[letter],
                axis_sign=sign,
                limits=(lo, hi),
                mirror=str(entry["mirror"]),
                mirror_sign=int(entry["mirror_sign"]),
            )
        )
    names = [d.name for d in dofs]
    if len(set(names)) != len(names):
        raise ValueError(f"{source_name}: duplicate dof names")
    by_name = {d.name: d for d in dofs}
    for d in dofs:
        m = by_name.get(d.mirror)
        if m is None:
            raise ValueError(f"{source_name}: dof {d.name!r} mirrors unknown dof {d.mirror!r}")
        if m.mirror != d.name or m.mirror_sign != d.mirror_sign:
            raise ValueError(f"{source_name}: mirror of {d.name!r} is not reciprocal")
        # Eq. 6 commutes with mirroring only if the mirrored range is the (signed) image.
        expect = d.limits if d.mirror_sign == 1 else (-d.limits[1], -d.limits[0])
        if not all(math.isclose(a, b, abs_tol=1e-9) for a, b in zip(expect, m.limits)):
            raise ValueError(
                f"{source_name}: limits of {d.name!r} and its mirror {m.name!r} disagree "
                f"with mirror_sign {d.mirror_sign}"
            )
    return DofTable(dofs=tuple(dofs), source=text)


def load_dof_table(path: str | Path = DEFAULT_DOF_TABLE) -> DofTable:
    """Read the DoF table from a YAML file (default: the packaged ``blsm/data/dofs.yaml``)."""
    path = Path(path)
    try:
        text = path.read_text()
    except OSError as exc:
        raise ValueError(f"{path}: cannot read DoF table ({exc.strerror})") from exc
    return parse_dof_table(text, str(path))


def angles_from_unconstrained(x: torch.Tensor, limits: torch.Tensor) -> torch.Tensor:
    """Eq. 6: map unconstrained pose values to joint angles inside their limits.

    Args:
        x: (B, D) unconstrained values.
        limits: (D, 2) ``[theta_min, theta_max]`` in radians.

    Returns:
        (B, D) angles in radians; ``x = 0`` gives the midpoint of each range.
    """
    half = 0.5 * (limits[:, 1] - limits[:, 0])
    mid = 0.5 * (limits[:, 0] + limits[:, 1])
    # The clamp only removes round-off at saturation (|x| large), where tanh's gradient is ~0.
    return torch.clamp(half * torch.tanh(x) + mid, limits[:, 0], limits[:, 1])


def unconstrained_from_angles(
    theta: torch.Tensor, limits: torch.Tensor, eps: float = 1e-6
) -> torch.Tensor:
    """Inverse of Eq. 6 (``atanh``), with angles on a limit pulled ``eps`` inside it.

    Args:
        theta: (B, D) angles in radians inside the limits.
        limits: (D, 2) ``[theta_min, theta_max]`` in radians.
        eps: how far inside (-1, 1) the normalised angle is clamped.

    Returns:
        (B, D) unconstrained values ``x``.
    """
    half = 0.5 * (limits[:, 1] - limits[:, 0])
    mid = 0.5 * (limits[:, 0] + limits[:, 1])
    u = ((theta - mid) / half).clamp(-1.0 + eps, 1.0 - eps)
    return torch.atanh(u)
