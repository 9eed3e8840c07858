"""Retargeting CMU clips onto BLSM, the motion library, the CLI, the preview and the limit chart."""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
import pytest
import torch

from blsm.cli import main
from blsm.joint_limits import angles_from_unconstrained
from blsm.mocap.bvh import BvhError, read_bvh
from blsm.mocap.library import load_clip, sha256
from blsm.mocap.retarget import load_map, retarget, select_map
from blsm.mocap.stats import limit_hits


@pytest.fixture(scope="module")
def library(tmp_path_factory, shared_mocap):
    """Two clips (a walk and a jump) imported at 10 fps with a short solve."""
    src = tmp_path_factory.mktemp("bvh")
    for name in ("002_01", "002_04"):
        shutil.copy(shared_mocap / f"{name}.bvh", src / f"{name}.bvh")
    out = tmp_path_factory.mktemp("lib") / "motions"
    rc = main(
        ["mocap", "import", str(src), "--out", str(out), "--fps", "10", "--iters", "80", "--workers", "1"]
    )
    assert rc == 0
    return src, out


def test_import_writes_one_file_per_clip_and_a_summary(library):
    src, out = library
    assert sorted(p.name for p in out.glob("*.npz")) == ["002_01.npz", "002_04.npz"]
    for extra in ("summary.csv", "limit_hits.png", "limit_hits.csv"):
        assert (out / extra).is_file()
    clip = load_clip(out / "002_01.npz")
    assert clip.fps == 10.0 and clip.num_frames == 29  # 171 frames at 60 fps
    assert clip.meta["source_sha256"] == sha256(src / "002_01.bvh")
    assert clip.meta["units"] == "cm" and clip.meta["mapping_table"] == "cc_base"
    assert clip.pose.shape == (29, 47) and clip.global_orient.shape == (29, 3)
    assert clip.segment_err_deg.shape == (29, len(clip.meta["segments"]))
    rows = (out / "summary.csv").read_text().splitlines()
    assert rows[0].startswith("clip,frames,fps,mpjpe_median_mm") and len(rows) == 3


def test_retargeted_body_follows_the_source(library, model):
    """Independent of the stored residuals: pose the model from the file and compare directions."""
    src, out = library
    clip = load_clip(out / "002_04.npz")
    assert float(np.median(clip.mpjpe_mm)) < 40.0
    assert float(clip.dir_err_mean_deg.mean()) < 10.0
    motion = read_bvh(src / "002_04.bvh", fps=10)
    _, pos = motion.global_transforms()
    n = motion.skeleton.names
    with torch.no_grad():
        o = model(
            pose=torch.as_tensor(clip.pose),
            global_orient=torch.as_tensor(clip.global_orient),
            transl=torch.as_tensor(clip.transl),
        )
    j = o.joints.double().numpy()
    b = model.bone_names

    def angle(u, v):
        u = u / np.linalg.norm(u, axis=-1, keepdims=True)
        v = v / np.linalg.norm(v, axis=-1, keepdims=True)
        return np.degrees(np.arccos(np.clip((u * v).sum(-1), -1, 1)))

    for (ba, bb), (sa, sb) in [
        (("hip_l", "knee_l"), ("CC_Base_L_Thigh", "CC_Base_L_Calf")),
        (("knee_r", "ankle_r"), ("CC_Base_R_Calf", "CC_Base_R_Foot")),
        (("shoulder_l", "elbow_l"), ("CC_Base_L_Upperarm", "CC_Base_L_Forearm")),
        (("elbow_r", "wrist_r"), ("CC_Base_R_Forearm", "CC_Base_R_Hand")),
    ]:
        err = angle(j[:, b.index(bb)] - j[:, b.index(ba)], pos[:, n.index(sb)] - pos[:, n.index(sa)])
        assert np.median(err) < 8.0, (ba, bb, np.median(err))
    # The root travels like the source's, scaled by the leg ratio; the feet meet the floor y = 0.
    root_src = pos[:, n.index("CC_Base_Pelvis")]
    np.testing.assert_allclose(
        j[:, 0, [0, 2]] - j[0, 0, [0, 2]],
        clip.meta["leg_ratio"] * (root_src[:, [0, 2]] - root_src[0, [0, 2]]),
        atol=1e-4,
    )
    lowest = o.vertices[..., 1].amin(-1).numpy()
    assert abs(float(np.percentile(lowest, 5))) < 0.01


def test_angles_stay_inside_the_limits(library, model):
    _, out = library
    for p in out.glob("*.npz"):
        ang = angles_from_unconstrained(
            torch.as_tensor(load_clip(p).pose).double(), model.dof_limits.double()
        )
        lo, hi = model.dof_limits.double().T
        assert bool(((ang >= lo) & (ang <= hi)).all())


def test_import_refuses_to_overwrite(library, capsys):
    src, out = library
    before = {p: p.stat().st_mtime_ns for p in out.iterdir()}
    assert main(["mocap", "import", str(src), "--out", str(out), "--fps", "10"]) == 2
    err = capsys.readouterr().err.strip()
    assert "already exists" in err and "--overwrite" in err and "\n" not in err
    assert {p: p.stat().st_mtime_ns for p in out.iterdir()} == before


def _corrupt(text: str, kind: str) -> tuple[str, int]:
    """A malformed copy of a CMU BVH and the line the error must name."""
    lines = text.splitlines()
    motion = lines.index("MOTION")
    first = motion + 4  # 1-based line of the first frame
    if kind == "truncated":
        return "\n".join(lines[: first + 9]) + "\n", first + 10
    if kind == "missing_channels":
        vals = lines[first + 4].split()
        lines[first + 4] = " ".join(vals[:-3])
        return "\n".join(lines) + "\n", first + 5
    if kind == "nan":
        vals = lines[first + 6].split()
        vals[7] = "nan"
        lines[first + 6] = " ".join(vals)
        return "\n".join(lines) + "\n", first + 7
    if kind == "unknown_joint":
        i = next(k for k, ln in enumerate(lines) if ln.strip() == "JOINT CC_Base_L_Calf")
        lines[i] = lines[i].replace("CC_Base_L_Calf", "CC_Base_L_Shin")
        root = next(k for k, ln in enumerate(lines) if ln.startswith("ROOT"))
        return "\n".join(lines) + "\n", root + 1
    raise AssertionError(kind)


@pytest.mark.parametrize("kind", ["truncated", "missing_channels", "nan", "unknown_joint"])
def test_malformed_bvh_is_one_line_nonzero_and_writes_nothing(tmp_path, shared_mocap, capsys, kind):
    src = tmp_path / "bvh"
    src.mkdir()
    shutil.copy(shared_mocap / "002_03.bvh", src / "002_03.bvh")  # a good clip next to the bad one
    bad, line = _corrupt((shared_mocap / "002_01.bvh").read_text(), kind)
    (src / "bad.bvh").write_text(bad)
    out = tmp_path / "lib"
    assert main(["mocap", "import", str(src), "--out", str(out), "--workers", "1"]) == 2
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0, err
    assert err.startswith(f"blsm: error: {src / 'bad.bvh'}:{line}: "), err
    assert not out.exists() or not any(out.iterdir())


def test_unknown_skeleton_names_the_missing_joint(tmp_path, shared_mocap):
    bad, line = _corrupt((shared_mocap / "002_03.bvh").read_text(), "unknown_joint")
    p = tmp_path / "x.bvh"
    p.write_text(bad)
    with pytest.raises(BvhError, match=rf"^{p}:{line}: unknown skeleton: no joint 'CC_Base_L_Calf'"):
        select_map(read_bvh(p))


def test_mapping_tables_are_validated(tmp_path):
    good = load_map(Path(__file__).resolve().parents[2] / "blsm" / "data" / "mocap_maps" / "cc_base.yaml")
    assert good.segments[0].label == "pelvis->neck" and len(good.orient) == 2
    bad = tmp_path / "bad.yaml"
    text = (Path(good.path)).read_text()
    bad.write_text(text.replace("[hip_l, knee_l, CC_Base_L_Thigh", "[knee_l, hip_l, CC_Base_L_Thigh"))
    with pytest.raises(ValueError, match=rf"^{bad}: segments\[3\] starts at 'knee_l'"):
        load_map(bad)
    bad.write_text(text.replace("CC_Base_L_Calf, 1.0]", "CC_Base_L_Calf, -1]", 1))
    with pytest.raises(ValueError, match="weight must be a positive number"):
        load_map(bad)


def test_retarget_api_on_a_short_run(model, shared_mocap):
    motion = read_bvh(shared_mocap / "002_03.bvh", fps=5)
    res = retarget(motion, model, first_iters=150, iters=60)
    assert res.mpjpe_mm.shape == (motion.num_frames,)
    assert np.median(res.mpjpe_mm) < 40
    assert np.all(res.dir_err_mean_deg < 15)
    assert 0.6 < res.leg_ratio < 1.0  # the mean Anny body (1.5 m) is smaller than the CMU subject


def test_limit_hits_count_frames_at_either_limit():
    limits = np.array([[-1.0, 1.0], [0.0, 2.0]])
    ang = np.array([[-1.0, 0.5], [0.0, 1.999], [0.999, 0.0], [0.2, 0.3]])
    h = limit_hits(ang, limits, ["a", "b"], tol_deg=1.0)
    np.testing.assert_allclose(h.lower, [0.25, 0.25])
    np.testing.assert_allclose(h.upper, [0.25, 0.25])
    assert h.flagged(0.2) == [("a", "min", 0.25), ("a", "max", 0.25), ("b", "min", 0.25), ("b", "max", 0.25)]
    assert h.flagged(0.3) == []


def test_preview_and_stats_write_pngs(library, tmp_path):
    from PIL import Image

    _, out = library
    png = tmp_path / "strip.png"
    assert main(["mocap", "preview", str(out / "002_04.npz"), "--out", str(png), "--frames", "3"]) == 0
    img = np.asarray(Image.open(png).convert("RGB")).astype(int)
    h = img.shape[0]
    assert img.shape[1] == 3 * 200
    top, bottom = img[20 : 20 + 280], img[300 : 300 + 280]
    assert (np.abs(top - 255).sum(-1) > 60).mean() > 0.002  # skeleton lines drawn
    assert (np.abs(bottom - 255).sum(-1) > 60).mean() > 0.05  # a body rendered
    assert h == 2 * 280 + 36
    chart = tmp_path / "hits.png"
    assert main(["mocap", "stats", str(out), "--out", str(chart)]) == 0
    assert chart.is_file() and chart.with_suffix(".csv").is_file()
    assert len(chart.with_suffix(".csv").read_text().splitlines()) == 48
