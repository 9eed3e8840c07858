from __future__ import annotations

import math

import pytest
import torch

from blsm.joint_limits import (
    DEFAULT_DOF_TABLE,
    angles_from_unconstrained,
    load_dof_table,
    parse_dof_table,
    unconstrained_from_angles,
)


def test_table_has_47_atoms_with_the_papers_joint_counts():
    table = load_dof_table()
    assert len(table) == 47
    per_joint: dict[str, int] = {}
    for d in table.dofs:
        per_joint[d.joint] = per_joint.get(d.joint, 0) + 1
    # Paper 000 Sec. 3.1: knee 1 DoF, wrist 2, neck 3.
    assert per_joint["knee_l"] == per_joint["knee_r"] == 1
    assert per_joint["wrist_l"] == per_joint["wrist_r"] == 2
    assert per_joint["neck"] == 3
    assert "pelvis" not in per_joint  # global orientation is separate from the 47


def test_every_range_contains_zero_and_is_anatomical():
    for d in load_dof_table().dofs:
        lo, hi = d.limits
        assert lo <= 0.0 <= hi
        assert hi - lo <= math.radians(200)
    knee = {d.name: d for d in load_dof_table().dofs}["knee_l.flex"]
    assert knee.limits[0] > math.radians(-15)  # no hyperextension beyond a straight leg


def test_mirror_signs_follow_from_the_frames():
    # Frames are mirror images with x negated, so a rotation about x keeps its sign and one about
    # y or z flips; the axis signs of the two atoms multiply in.
    table = load_dof_table()
    by_name = {d.name: d for d in table.dofs}
    for d in table.dofs:
        m = by_name[d.mirror]
        assert m.axis == d.axis
        expected = d.axis_sign * m.axis_sign * (1 if d.axis == 0 else -1)
        assert d.mirror_sign == expected, d.name


def test_eq6_stays_inside_limits_and_midpoint_at_zero(gen):
    limits = load_dof_table().limits_tensor()
    x = torch.randn(1000, 47, generator=gen, dtype=torch.float64) * 20
    x[0] = float("inf")
    x[1] = -float("inf")
    theta = angles_from_unconstrained(x, limits)
    assert (theta >= limits[:, 0]).all() and (theta <= limits[:, 1]).all()
    mid = angles_from_unconstrained(torch.zeros(1, 47, dtype=torch.float64), limits)
    assert torch.allclose(mid[0], limits.mean(1), atol=0, rtol=0)


def test_inverse_round_trip(gen):
    limits = load_dof_table().limits_tensor()
    x = torch.randn(50, 47, generator=gen, dtype=torch.float64)
    back = unconstrained_from_angles(angles_from_unconstrained(x, limits), limits)
    assert torch.allclose(back, x, atol=1e-8)


def test_bad_tables_raise_naming_the_file(tmp_path):
    text = DEFAULT_DOF_TABLE.read_text()
    bad = tmp_path / "dofs.yaml"
    bad.write_text(text.replace("min: -10, max: 140", "min: 10, max: 140", 1))
    with pytest.raises(ValueError, match="dofs.yaml.*knee_l.flex.*contain 0"):
        load_dof_table(bad)
    bad.write_text(text.replace("mirror: knee_r.flex", "mirror: knee_x.flex", 1))
    with pytest.raises(ValueError, match="unknown dof"):
        load_dof_table(bad)
    with pytest.raises(ValueError, match="not valid YAML"):
        parse_dof_table("dofs: [", "x.yaml")
    with pytest.raises(ValueError, match="cannot read"):
        load_dof_table(tmp_path / "missing.yaml")
