"""BVH reading: hierarchy, channel orders, units, resampling, and one-line errors for bad files."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from blsm.mocap.bvh import BvhError, infer_units, read_bvh, resample

# A three-joint chain: root with 6 channels (ZXY), a child with XYZ order, an End Site.
SMALL = """HIERARCHY
ROOT Hips
{
  OFFSET 0 0 0
  CHANNELS 6 Xposition Yposition Zposition Zrotation Xrotation Yrotation
  JOINT Knee
  {
    OFFSET 0 -45 0
    CHANNELS 3 Xrotation Yrotation Zrotation
    JOINT Ankle
    {
      OFFSET 0 -40 5
      CHANNELS 3 Zrotation Yrotation Xrotation
      End Site
      {
        OFFSET 0 0 15
      }
    }
  }
}
MOTION
Frames: 3
Frame Time: 0.0333333
10 90 0 30 20 10 40 0 0 0 0 0
10 90 10 0 0 0 0 0 0 0 0 0
10 90 20 0 0 90 0 90 0 0 0 0
"""


def write(tmp_path: Path, text: str, name: str = "clip.bvh") -> Path:
    p = tmp_path / name
    p.write_text(text)
    return p


def test_channels_in_any_order_and_forward_kinematics(tmp_path):
    m = read_bvh(write(tmp_path, SMALL), units="cm")
    assert m.skeleton.names == ["Hips", "Knee", "Ankle"]
    assert m.skeleton.parents == [-1, 0, 1]
    assert m.num_frames == 3 and m.fps == pytest.approx(30.0, rel=1e-5)
    rot, pos = m.global_transforms()
    # Frame 0 by hand: root R = Rz(30) Rx(20) Ry(10) (listed order), knee R = Rx(40).
    r_root = Rotation.from_euler("ZXY", [30, 20, 10], degrees=True).as_matrix()
    r_knee = Rotation.from_euler("XYZ", [40, 0, 0], degrees=True).as_matrix()
    root = np.array([0.10, 0.90, 0.0])
    knee = root + r_root @ np.array([0, -0.45, 0])
    ankle = knee + r_root @ r_knee @ np.array([0, -0.40, 0.05])
    np.testing.assert_allclose(pos[0], np.stack([root, knee, ankle]), atol=1e-12)
    np.testing.assert_allclose(rot[0, 2], r_root @ r_knee, atol=1e-12)
    # Position channels add to the OFFSET; frame 2 has pure 90 degree turns.
    np.testing.assert_allclose(pos[1, 0], [0.10, 0.90, 0.10], atol=1e-12)
    np.testing.assert_allclose(m.skeleton.end_sites[2], [0, 0, 0.15])


def test_units_are_inferred_from_the_skeleton_size(tmp_path):
    # A 1.75 m tall chain: in cm, in m and in inches.
    tall = SMALL.replace("OFFSET 0 -45 0", "OFFSET 0 -90 0").replace("OFFSET 0 -40 5", "OFFSET 0 -85 5")
    cm = read_bvh(write(tmp_path, tall))
    assert cm.units == "cm" and cm.units_inferred
    metres = tall.replace("OFFSET 0 -90 0", "OFFSET 0 -0.90 0").replace(
        "OFFSET 0 -85 5", "OFFSET 0 -0.85 0.05"
    )
    metres = metres.replace("OFFSET 0 0 15", "OFFSET 0 0 0.15")
    m = read_bvh(write(tmp_path, metres, "m.bvh"))
    assert m.units == "m"
    np.testing.assert_allclose(m.skeleton.offsets, cm.skeleton.offsets, atol=1e-12)
    assert infer_units(m.skeleton) == "m"
    inches = tall.replace("OFFSET 0 -90 0", "OFFSET 0 -35.4 0").replace("OFFSET 0 -85 5", "OFFSET 0 -33.5 2")
    assert read_bvh(write(tmp_path, inches.replace("OFFSET 0 0 15", "OFFSET 0 0 6"), "in.bvh")).units == "in"
    # Declared units win over inference.
    assert read_bvh(write(tmp_path, SMALL), units="m").skeleton.offsets[1, 1] == -45.0
    with pytest.raises(ValueError, match="units"):
        read_bvh(write(tmp_path, SMALL), units="furlong")


def test_resample_halves_the_rate_with_slerp(tmp_path):
    m = read_bvh(write(tmp_path, SMALL), units="cm")
    r = resample(m, 15.0)
    assert r.num_frames == 2 and r.fps == 15.0
    np.testing.assert_allclose(r.rotations[1], m.rotations[2], atol=1e-9)
    up = resample(m, 60.0)
    assert up.num_frames == 5
    # Half way between frame 1 (identity) and frame 2 (90 deg turns) is a 45 degree slerp.
    half = Rotation.from_matrix(up.rotations[3, 0]).magnitude()
    full = Rotation.from_matrix(m.rotations[2, 0]).magnitude()
    assert half == pytest.approx(full / 2, abs=1e-5)  # Frame Time is rounded
    np.testing.assert_allclose(up.translations[3, 0], [0.10, 0.90, 0.15], atol=1e-6)


@pytest.mark.parametrize(
    "edit, line, message",
    [
        (lambda s: s.replace("10 90 20 0 0 90 0 90 0 0 0 0\n", ""), 26, "truncated motion"),
        (lambda s: s.replace("10 90 10 0 0 0 0 0 0 0 0 0", "10 90 10 0 0 0 0 0 0"), 25, "has 9 values"),
        (lambda s: s.replace("10 90 10 0 0 0 0 0 0 0 0 0", "10 90 nan 0 0 0 0 0 0 0 0 0"), 25, "non-finite"),
        (lambda s: s.replace("10 90 10 0 0 0 0 0 0 0 0 0", "10 90 1O 0 0 0 0 0 0 0 0 0"), 25, "not a number"),
        (
            lambda s: s.replace("CHANNELS 3 Xrotation Yrotation Zrotation", "CHANNELS 3 Xrotation Yrotation"),
            9,
            "CHANNELS says 3",
        ),
        (
            lambda s: s.replace(
                "CHANNELS 3 Xrotation Yrotation Zrotation", "CHANNELS 3 Xrotation Yrotation Wrotation"
            ),
            9,
            "unknown channel",
        ),
        (lambda s: s.replace("JOINT Ankle", "JIONT Ankle"), 10, "unknown keyword"),
        (lambda s: s.replace("    OFFSET 0 -40 5\n", ""), 17, "has no OFFSET"),
        (lambda s: s.replace("Frame Time: 0.0333333", "Frame Time: 0"), 23, "must be positive"),
        (lambda s: s.replace("Frames: 3", "Frames: three"), 22, "not an integer"),
        (lambda s: s[: s.index("MOTION")], 20, "missing 'MOTION'"),
    ],
)
def test_malformed_files_give_one_line_naming_file_and_line(tmp_path, edit, line, message):
    p = write(tmp_path, edit(SMALL))
    with pytest.raises(BvhError) as exc:
        read_bvh(p)
    text = str(exc.value)
    assert "\n" not in text
    assert text.startswith(f"{p}:{line}: "), text
    assert message in text


def test_extra_frames_and_missing_file_are_errors(tmp_path):
    p = write(tmp_path, SMALL + "1 2 3 4 5 6 7 8 9 10 11 12\n")
    with pytest.raises(BvhError, match=rf"^{p}:27: more frame lines"):
        read_bvh(p)
    with pytest.raises(BvhError, match="cannot read"):
        read_bvh(tmp_path / "absent.bvh")


def test_shared_cmu_clip_reads(shared_mocap):
    m = read_bvh(shared_mocap / "002_01.bvh")
    assert m.units == "cm" and m.units_inferred
    assert m.fps == pytest.approx(60.0, rel=1e-3)
    assert m.num_frames == 171
    _, pos = m.global_transforms()
    names = m.skeleton.names
    # A person: head about 1.6-1.8 m above the feet, thigh about 45-50 cm.
    head = pos[:, names.index("CC_Base_Head"), 1]
    foot = pos[:, names.index("CC_Base_L_Foot"), 1]
    assert 1.3 < float(np.median(head - foot)) < 1.8
    thigh = np.linalg.norm(
        pos[:, names.index("CC_Base_L_Calf")] - pos[:, names.index("CC_Base_L_Thigh")], axis=-1
    )
    assert 0.4 < thigh.mean() < 0.55 and thigh.std() < 1e-6
    assert math.isclose(resample(m, 30).num_frames, 86)
