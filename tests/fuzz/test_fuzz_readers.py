"""Fuzz corpus over the readers (issue 17): malformed datasets, BVH files, model, motion and prior
files, checkpoints, images and configs, made by the tests themselves.

Every case checks the README's promise for bad input: one line ``<prog>: error: <path>: <problem>``
on stderr naming the file, exit status 2 (``synth validate`` reports a damaged dataset as failures
with status 1, as documented), no traceback, and no new file or folder. The dataset loader raises an
error naming the shard and the sample, in the main process and in DataLoader workers, and never
hangs. Valid files with CRLF line endings or a UTF-8 byte order mark import like any other.
"""

from __future__ import annotations

import io
import json
import shutil
import sys
import tarfile
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest
import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "synth"))
from fakes import make_dataset  # noqa: E402

import blsm.cli  # noqa: E402
import recovery.cli  # noqa: E402
import synth.cli  # noqa: E402
from blsm.mocap.library import load_clip  # noqa: E402
from blsm.mocap.prior import load_prior  # noqa: E402
from synth.dataset.images import SynthDataset  # noqa: E402
from synth.dataset.index import DatasetIndex  # noqa: E402

ROOT = Path(__file__).resolve().parents[2]
CMU = ROOT.parent / "shared" / "mocap" / "cmu"
MAINS = {"blsm": blsm.cli.main, "synth": synth.cli.main, "recovery": recovery.cli.main}


# ------------------------------------------------------------------------------------------------
# helpers


def _listing(folder: Path) -> set[str]:
    return {str(p.relative_to(folder)) for p in folder.rglob("*")}


def _run(capsys, prog: str, argv: list[str]) -> tuple[int, str, str]:
    capsys.readouterr()
    try:
        rc = MAINS[prog.split()[0]](argv)
    except SystemExit as exc:  # argparse
        rc = exc.code
    out, err = capsys.readouterr()
    return rc, out, err


def _bad_input(capsys, prog: str, argv: list[str], watch: Path, *needles: str, status: int = 2) -> str:
    """``prog argv`` fails with ``status``, one stderr line naming ``needles``, nothing new in ``watch``."""
    before = _listing(watch)
    rc, out, err = _run(capsys, prog, argv)
    assert "Traceback" not in err + out, err
    lines = err.strip().splitlines()
    assert rc == status, (rc, err)
    assert len(lines) == 1, err
    assert lines[0].startswith(f"{prog}: error: "), lines[0]
    for n in needles:
        assert str(n) in lines[0], (n, lines[0])
    assert _listing(watch) == before, _listing(watch) ^ before
    return lines[0]


def _one_line_error(call: Callable[[], object], *needles: str) -> str:
    with pytest.raises(ValueError) as info:
        call()
    msg = str(info.value)
    assert "\n" not in msg, msg
    for n in needles:
        assert str(n) in msg, (n, msg)
    return msg


# ------------------------------------------------------------------------------------------------
# synth datasets: validate, export, SynthDataset


@pytest.fixture(scope="module")
def dataset(tmp_path_factory, model) -> Path:
    """A complete fake dataset (tests/synth/fakes.py): 4 images in 2 shards."""
    return make_dataset(tmp_path_factory.mktemp("fuzz_ds") / "ds", num=4, shard_size=2, size=(96, 88), model=model)


def _member(root: Path, key: str, name: str) -> tuple[Path, int, int]:
    index = DatasetIndex(root)
    i = next(i for i, (_, k, _) in enumerate(index.samples) if k == key)
    s, _, members = index.samples[i]
    return index.shards[s], *members[name]


def _rewrite_member(root: Path, key: str, name: str, edit: Callable[[bytes], bytes]) -> Path:
    """Rewrite one member of a shard (a valid tar; the manifest's SHA-256 is left as it was)."""
    shard, _, _ = _member(root, key, name)
    buf = io.BytesIO()
    with tarfile.open(shard) as src, tarfile.open(fileobj=buf, mode="w", format=tarfile.USTAR_FORMAT) as dst:
        for m in src:
            data = src.extractfile(m).read()
            if m.name == f"{key}.{name}":
                data = edit(data)
                m.size = len(data)
            dst.addfile(m, io.BytesIO(data))
    shard.write_bytes(buf.getvalue())
    return shard


def _edit_json(edit: Callable[[dict], None]) -> Callable[[bytes], bytes]:
    def apply(data: bytes) -> bytes:
        doc = json.loads(data)
        edit(doc)
        return json.dumps(doc).encode()

    return apply


def _flip(path: Path, offset: int) -> Path:
    data = bytearray(path.read_bytes())
    data[offset] ^= 0xFF
    path.write_bytes(bytes(data))
    return path


def _damage(root: Path, kind: str) -> tuple[str, str]:
    """Damage a copy of the dataset; return (the file the loader must name, what it must say)."""
    s0, s1 = root / "shard-000000.tar", root / "shard-000001.tar"
    if kind == "flipped_png_byte":  # inside sample 3's image data
        shard, offset, size = _member(root, "000000003", "rgb.png")
        _flip(shard, offset + size // 2)
        return f"{shard}:000000003.rgb.png", "not a readable PNG"
    if kind == "flipped_header_byte":  # a tar header: its checksum fails
        _flip(s0, 10)
        return str(s0), "not a readable shard"
    if kind == "flipped_json_byte":  # sample 1's label no longer parses
        shard, offset, _ = _member(root, "000000001", "json")
        _flip(shard, offset)
        return f"{shard}:000000001.json", "not valid JSON"
    if kind == "truncated_tar":
        s1.write_bytes(s1.read_bytes()[: s1.stat().st_size // 2])
        return str(s1), "shard"
    if kind == "zero_byte_shard":
        s1.write_bytes(b"")
        return str(s1), "shard"
    if kind == "garbage_shard":
        s1.write_bytes(np.random.default_rng(0).bytes(s1.stat().st_size))
        return str(s1), "not a readable shard"
    if kind == "missing_shard":
        s1.unlink()
        return str(s1), "missing"
    if kind == "edited_label_camera":  # parses, but its camera K is not 3 x 3: found on reading
        shard = _rewrite_member(root, "000000002", "json", _edit_json(lambda d: d["camera"].update(K=[[1, 0], [0, 1]])))
        return f"{shard}:000000002.json", "bad labels"
    if kind == "edited_label_people":  # a person without keypoints: found when indexing
        shard = _rewrite_member(root, "000000000", "json", _edit_json(lambda d: d["people"][0].pop("visible")))
        return f"{shard}:000000000.json", "bad labels"
    if kind == "missing_member":
        shard = s0
        buf = io.BytesIO()
        with tarfile.open(shard) as src, tarfile.open(fileobj=buf, mode="w") as dst:
            for m in src:
                if m.name != "000000001.mask.png":
                    dst.addfile(m, src.extractfile(m))
        shard.write_bytes(buf.getvalue())
        return f"{shard}", "000000001"
    raise AssertionError(kind)


SHARD_DAMAGE = [
    "flipped_png_byte",
    "flipped_header_byte",
    "flipped_json_byte",
    "truncated_tar",
    "zero_byte_shard",
    "garbage_shard",
    "missing_shard",
    "edited_label_camera",
    "edited_label_people",
    "missing_member",
]
AT_ITEM = {"flipped_png_byte", "edited_label_camera"}  # found when the item is read, not when indexed


@pytest.fixture
def damaged(dataset, tmp_path) -> Callable[[str], tuple[Path, str, str]]:
    def make(kind: str) -> tuple[Path, str, str]:
        root = tmp_path / "ds"
        shutil.copytree(dataset, root)
        return root, *_damage(root, kind)

    return make


@pytest.mark.parametrize("kind", SHARD_DAMAGE)
def test_loader_names_the_shard_and_sample(damaged, kind):
    root, where, what = damaged(kind)
    if kind not in AT_ITEM:
        _one_line_error(lambda: SynthDataset(root, crop=32), where, what)
        return
    ds = SynthDataset(root, crop=32)
    key = where.rsplit(":", 1)[1].split(".")[0]
    bad = [j for j, (s, _) in enumerate(ds.items) if ds.index.samples[s][1] == key]
    _one_line_error(lambda: ds[bad[0]], where, what)


@pytest.mark.parametrize("kind", sorted(AT_ITEM))
@pytest.mark.parametrize("workers", [0, 2])
def test_dataloader_raises_naming_the_sample_and_never_hangs(damaged, kind, workers):
    root, where, what = damaged(kind)
    ds = SynthDataset(root, crop=32)
    loader = torch.utils.data.DataLoader(ds, batch_size=2, num_workers=workers, timeout=60 if workers else 0)
    with pytest.raises(ValueError) as info:
        for _ in loader:
            pass
    # A worker's error comes back wrapped in torch's text; the CLIs print the worker's own line.
    assert where in str(info.value) and what in str(info.value)
    line = recovery.cli.error_line(info.value)
    assert "\n" not in line and where in line and what in line, line


@pytest.mark.parametrize("kind", SHARD_DAMAGE)
@pytest.mark.parametrize("fmt", ["spin", "coco"])
def test_export_refuses_a_damaged_dataset(damaged, kind, fmt, capsys, tmp_path):
    root, where, _ = damaged(kind)
    shard = where.split(":")[0]
    _bad_input(capsys, "synth", ["export", str(root), "--format", fmt, "--out", str(tmp_path / "o")], tmp_path, shard)


@pytest.mark.parametrize("kind", ["flipped_png_byte", "truncated_tar", "garbage_shard", "missing_shard", "edited_label_camera"])
def test_validate_reports_a_damaged_shard(damaged, kind, capsys, tmp_path):
    root, where, _ = damaged(kind)
    shard = where.split(":")[0]
    before = _listing(tmp_path)
    rc, out, err = _run(capsys, "synth", ["validate", str(root)])
    assert rc == 1 and "Traceback" not in out + err
    assert any(ln.startswith(f"FAIL {shard}: ") for ln in out.splitlines()), out
    assert _listing(tmp_path) == before


def _manifest(root: Path, kind: str) -> None:
    man = root / "manifest.json"
    if kind == "missing":
        man.unlink()
    elif kind == "garbage":
        man.write_bytes(np.random.default_rng(1).bytes(300))
    elif kind == "list":
        man.write_text("[1, 2]")
    elif kind == "other_format":
        man.write_text(json.dumps({**json.loads(man.read_text()), "format": "other"}))
    elif kind == "shards_not_a_table":
        man.write_text(json.dumps({**json.loads(man.read_text()), "shards": ["shard-000000.tar"]}))
    elif kind == "folder":
        man.unlink()
        man.mkdir()
    else:
        raise AssertionError(kind)


MANIFEST_DAMAGE = ["missing", "garbage", "list", "other_format", "shards_not_a_table", "folder"]


@pytest.mark.parametrize("kind", MANIFEST_DAMAGE)
@pytest.mark.parametrize("command", ["validate", "export", "loader"])
def test_a_bad_manifest_is_one_line(dataset, tmp_path, capsys, kind, command):
    root = tmp_path / "ds"
    shutil.copytree(dataset, root)
    _manifest(root, kind)
    man = root / "manifest.json"
    if command == "loader":
        _one_line_error(lambda: SynthDataset(root, crop=32), man)
    elif command == "validate":
        _bad_input(capsys, "synth", ["validate", str(root)], tmp_path, man)
    else:
        _bad_input(capsys, "synth", ["export", str(root), "--format", "spin", "--out", str(tmp_path / "o")], tmp_path, man)


def test_validate_a_missing_subject_file(dataset, tmp_path, capsys):
    """The subject index lists a file that is not there: a failure naming it, no traceback."""
    root = tmp_path / "ds"
    shutil.copytree(dataset, root)
    (root / "subjects").mkdir()
    (root / "subjects" / "index.json").write_text(json.dumps({"subjects": {"fake0": "0" * 64}}))
    rc, out, err = _run(capsys, "synth", ["validate", str(root)])
    assert rc == 1 and "Traceback" not in out + err
    assert f"FAIL {root / 'subjects' / 'fake0.npz'}: missing" in out, out


def test_validate_a_missing_folder(tmp_path, capsys):
    _bad_input(capsys, "synth", ["validate", str(tmp_path / "nowhere")], tmp_path, tmp_path / "nowhere")


# ------------------------------------------------------------------------------------------------
# BVH files: blsm mocap import

TINY_BVH = """HIERARCHY
ROOT Hips
{
  OFFSET 0 0 0
  CHANNELS 6 Xposition Yposition Zposition Zrotation Yrotation Xrotation
  JOINT Spine
  {
    OFFSET 0 50 0
    CHANNELS 3 Zrotation Yrotation Xrotation
    End Site
    {
      OFFSET 0 50 0
    }
  }
}
MOTION
Frames: 2
Frame Time: 0.033333
0 90 0 0 0 0 0 0 0
0 90 0 0 10 0 0 5 0
"""


def _bvh(kind: str) -> tuple[bytes, str]:
    """A malformed BVH file and what the error says (``LINE: problem``)."""
    if kind == "zero_frames":
        return TINY_BVH.replace("Frames: 2", "Frames: 0").split("Frame Time")[0].encode() + b"Frame Time: 0.03\n", "17: Frames: must be at least 1"
    if kind == "binary_garbage":
        return np.random.default_rng(2).bytes(4000), "not a text file"
    if kind == "nul_bytes":
        return b"\0" * 100, "1: expected 'HIERARCHY'"
    if kind == "huge_value":
        return TINY_BVH.replace("0 90 0 0 10 0", "0 1e30 0 0 10 0").encode(), "20: frame 2: value 1e+30 in channel 2 is out of range"
    if kind == "huge_offset":
        return TINY_BVH.replace("OFFSET 0 50 0\n    CHANNELS", "OFFSET 0 1e30 0\n    CHANNELS").encode(), "8: OFFSET: value 1e30 is out of range"
    if kind == "nan":
        return TINY_BVH.replace("0 0 10 0 0 5 0", "0 0 nan 0 0 5 0").encode(), "20: frame 2: non-finite"
    if kind == "inf":
        return TINY_BVH.replace("0 0 10 0 0 5 0", "0 0 inf 0 0 5 0").encode(), "20: frame 2: non-finite"
    if kind == "no_hierarchy":
        return TINY_BVH.replace("HIERARCHY\n", "").encode(), "1: expected 'HIERARCHY'"
    if kind == "truncated_motion":
        return TINY_BVH.rsplit("0 90 0 0 10", 1)[0].encode(), "20: truncated motion"
    if kind == "motion_cut_in_a_frame":
        return TINY_BVH[:-8].encode(), "20: frame 2 has 5 values"
    if kind == "no_motion":
        return TINY_BVH.split("MOTION")[0].encode(), "missing 'MOTION'"
    if kind == "empty":
        return b"", "unexpected end of file"
    if kind == "crlf_and_bom_but_broken":  # the BOM is not the problem; the NaN is
        return b"\xef\xbb\xbf" + TINY_BVH.replace("0 0 10 0 0 5 0", "0 0 nan 0 0 5 0").replace("\n", "\r\n").encode(), "20: frame 2: non-finite"
    raise AssertionError(kind)


BVH_DAMAGE = ["zero_frames", "binary_garbage", "nul_bytes", "huge_value", "huge_offset", "nan", "inf",
              "no_hierarchy", "truncated_motion", "motion_cut_in_a_frame", "no_motion", "empty",
              "crlf_and_bom_but_broken"]


@pytest.mark.parametrize("kind", BVH_DAMAGE)
def test_malformed_bvh_is_one_line(tmp_path, capsys, kind):
    src = tmp_path / "bvh"
    src.mkdir()
    data, problem = _bvh(kind)
    (src / "bad.bvh").write_bytes(data)
    msg = _bad_input(
        capsys, "blsm", ["mocap", "import", str(src), "--out", str(tmp_path / "lib"), "--workers", "1"],
        tmp_path, f"{src / 'bad.bvh'}:",
    )
    assert problem in msg, msg


def _cmu(frames: int) -> str:
    """The CMU clip 002_01 cut to its first ``frames`` frames."""
    lines = (CMU / "002_01.bvh").read_text().splitlines()
    m = lines.index("MOTION")
    return "\n".join([*lines[: m + 1], f"Frames: {frames}", lines[m + 2], *lines[m + 3 : m + 3 + frames]]) + "\n"


@pytest.mark.parametrize("kind", ["crlf", "bom", "crlf_bom", "one_frame"])
def test_valid_bvh_with_crlf_bom_or_one_frame_imports(tmp_path, capsys, kind):
    if not (CMU / "002_01.bvh").is_file():
        pytest.skip(f"needs the shared CMU mocap clips at {CMU} (not present on this machine)")
    text = _cmu(1 if kind == "one_frame" else 3)
    data = text.replace("\n", "\r\n") if "crlf" in kind else text
    raw = (b"\xef\xbb\xbf" if "bom" in kind else b"") + data.encode()
    src = tmp_path / "bvh"
    src.mkdir()
    (src / "clip.bvh").write_bytes(raw)
    out = tmp_path / "lib"
    rc, _, err = _run(capsys, "blsm", ["mocap", "import", str(src), "--out", str(out), "--workers", "1", "--iters", "3"])
    assert rc == 0, err
    clip = load_clip(out / "clip.npz")
    assert clip.num_frames == (1 if kind == "one_frame" else 3)
    assert np.isfinite(clip.pose).all()


# ------------------------------------------------------------------------------------------------
# model, motion-clip and pose-prior files


def _npz_bytes(**arrays) -> bytes:
    buf = io.BytesIO()
    np.savez(buf, **arrays)
    return buf.getvalue()


@pytest.fixture(scope="module")
def good_files(tmp_path_factory, model) -> dict[str, Path]:
    """A valid model file (the packaged one), motion clip and pose prior."""
    from blsm.mocap.library import MotionClip, save_clip
    from blsm.mocap.prior import DEFAULT_PRIOR
    from blsm.model import DEFAULT_MODEL

    t = 3
    clip = MotionClip(
        name="walk", fps=30.0, pose=np.zeros((t, 47)), global_orient=np.zeros((t, 3)), transl=np.zeros((t, 3)),
        dir_err_mean_deg=np.zeros(t), dir_err_max_deg=np.zeros(t), mpjpe_mm=np.zeros(t),
        segment_err_deg=np.zeros((t, 1)), meta={"dof_names": model.dof_names, "segments": ["a->b"]},
    )
    root = tmp_path_factory.mktemp("fuzz_files")
    return {"model": DEFAULT_MODEL, "clip": save_clip(clip, root / "walk.npz"), "prior": DEFAULT_PRIOR}


def _arrays(path: Path) -> dict[str, np.ndarray]:
    with np.load(path, allow_pickle=False) as npz:
        return {k: npz[k] for k in npz.files}


def _bad_file(good: Path, what: str, kind: str, dst: Path) -> tuple[Path, str]:
    """A malformed copy of a model / clip / prior file and what the error says."""
    data = good.read_bytes()
    arrays = _arrays(good)
    if kind == "zero_byte":
        dst.write_bytes(b"")
        return dst, "not a readable .npz"
    if kind == "truncated":
        dst.write_bytes(data[: len(data) // 2])
        return dst, "not a readable .npz"
    if kind == "random_bytes":
        dst.write_bytes(np.random.default_rng(3).bytes(len(data) // 4 + 100))
        return dst, "not a readable .npz"
    if kind == "flipped_byte":  # in the middle of the compressed data: a CRC or zlib error
        raw = bytearray(data)
        raw[len(raw) // 2] ^= 0xFF
        dst.write_bytes(bytes(raw))
        return dst, "not a readable .npz"
    if kind == "folder":
        dst.mkdir()
        return dst, f"no such {what} file"
    if kind == "wrong_version":
        if what == "motion":
            meta = json.loads(str(arrays["meta"]))
            arrays["meta"] = np.array(json.dumps({**meta, "version": 99}))
        else:
            arrays["format_version"] = np.array(99)
        dst.write_bytes(_npz_bytes(**arrays))
        return dst, "version 99 is not supported"
    if kind == "no_version":
        if what == "motion":
            meta = json.loads(str(arrays["meta"]))
            meta.pop("version")
            arrays["meta"] = np.array(json.dumps(meta))
        else:
            arrays.pop("format_version")
        dst.write_bytes(_npz_bytes(**arrays))
        return dst, "version"
    if kind == "missing_array":
        gone = {"model": "weights", "motion": "pose", "pose prior": "means"}[what]
        arrays.pop(gone)
        dst.write_bytes(_npz_bytes(**arrays))
        return dst, f"missing array {gone!r}"
    if kind == "meta_not_an_object":
        key = "meta" if what == "motion" else "meta_json"
        arrays[key] = np.array("[1, 2, 3]")
        dst.write_bytes(_npz_bytes(**arrays))
        return dst, "meta"
    if kind == "nan":
        key = {"model": "template", "motion": "pose", "pose prior": "means"}[what]
        arrays[key] = np.full_like(arrays[key], np.nan)
        dst.write_bytes(_npz_bytes(**arrays))
        return dst, "non-finite" if what != "model" else "NaN"
    if kind == "npy_not_npz":
        buf = io.BytesIO()
        np.save(buf, np.zeros(3))
        dst.write_bytes(buf.getvalue())
        return dst, "not a"
    raise AssertionError(kind)


FILE_DAMAGE = ["zero_byte", "truncated", "random_bytes", "flipped_byte", "folder", "wrong_version", "no_version",
               "missing_array", "meta_not_an_object", "nan", "npy_not_npz"]
LOADERS = {"model": lambda p: __import__("blsm").load(p), "motion": load_clip, "pose prior": load_prior}
KEYS = {"model": "model", "motion": "clip", "pose prior": "prior"}


@pytest.mark.parametrize("kind", FILE_DAMAGE)
@pytest.mark.parametrize("what", ["model", "motion", "pose prior"])
def test_bad_model_clip_and_prior_files_are_one_line(good_files, tmp_path, what, kind):
    path, problem = _bad_file(good_files[KEYS[what]], what, kind, tmp_path / "bad.npz")
    _one_line_error(lambda: LOADERS[what](path), f"{path}: ", problem)


@pytest.mark.parametrize("kind", ["truncated", "wrong_version", "missing_array"])
def test_commands_that_take_a_model_file(good_files, tmp_path, capsys, kind):
    bad, problem = _bad_file(good_files["model"], "model", kind, tmp_path / "bad.npz")
    out = tmp_path / "out"
    _bad_input(capsys, "blsm", ["info", "--model", str(bad)], tmp_path, bad, problem)
    _bad_input(capsys, "blsm", ["demo", "--model", str(bad), "--out", str(out), "--n", "1"], tmp_path, bad, problem)
    _bad_input(capsys, "blsm", ["atoms", "--model", str(bad), "--out", str(out)], tmp_path, bad, problem)
    src = tmp_path / "bvh"
    src.mkdir()
    (src / "a.bvh").write_text(TINY_BVH)
    _bad_input(capsys, "blsm", ["mocap", "import", str(src), "--out", str(out), "--model", str(bad)], tmp_path, bad)
    scan = tmp_path / "scan.npz"
    scan.write_bytes(b"")
    _bad_input(capsys, "blsm register", ["register", str(scan), "--out", str(out), "--model", str(bad)], tmp_path, bad)


@pytest.mark.parametrize("kind", ["truncated", "wrong_version", "missing_array"])
def test_commands_that_take_clips_and_priors(good_files, tmp_path, capsys, kind):
    lib = tmp_path / "lib"
    lib.mkdir()
    shutil.copy(good_files["clip"], lib / "walk.npz")
    bad, problem = _bad_file(good_files["clip"], "motion", kind, lib / "run.npz")
    _bad_input(capsys, "blsm", ["mocap", "preview", str(bad), "--out", str(tmp_path / "p.png")], tmp_path, bad, problem)
    _bad_input(capsys, "blsm", ["mocap", "stats", str(lib), "--out", str(tmp_path / "s.png")], tmp_path, bad, problem)
    _bad_input(capsys, "blsm", ["mocap", "fit-prior", str(lib), "--out", str(tmp_path / "p.npz")], tmp_path, bad, problem)
    out = tmp_path / "ds"
    cfg = tmp_path / "lib.yaml"
    cfg.write_text(f"num: 2\nposes: {{source: library, library: {lib}}}\n")
    _bad_input(capsys, "synth", ["generate", str(cfg), "--out", str(out)], tmp_path, bad, problem)
    prior, problem = _bad_file(good_files["prior"], "pose prior", kind, tmp_path / "prior.npz")
    cfg.write_text(f"num: 2\nposes: {{source: prior, prior: {prior}}}\n")
    _bad_input(capsys, "synth", ["generate", str(cfg), "--out", str(out)], tmp_path, prior, problem)


# ------------------------------------------------------------------------------------------------
# recovery: checkpoints, images, configs, datasets


def _bad_checkpoint(kind: str, dst: Path) -> tuple[Path, str]:
    if kind == "zero_byte":
        dst.write_bytes(b"")
    elif kind == "random_bytes":
        dst.write_bytes(np.random.default_rng(4).bytes(5000))
    elif kind == "truncated":
        buf = io.BytesIO()
        torch.save({"format": "recovery-checkpoint", "weights": torch.zeros(1000)}, buf)
        dst.write_bytes(buf.getvalue()[:1500])
    elif kind == "foreign":
        torch.save({"weights": torch.zeros(2)}, dst)
        return dst, "not a 'recovery-checkpoint' file"
    elif kind == "folder":
        dst.mkdir()
        return dst, "no such checkpoint"
    elif kind == "missing":
        return dst, "no such checkpoint"
    else:
        raise AssertionError(kind)
    return dst, "corrupt checkpoint"


@pytest.mark.parametrize("kind", ["zero_byte", "random_bytes", "truncated", "foreign", "folder", "missing"])
def test_recovery_bad_checkpoints(dataset, tmp_path, capsys, kind):
    ck, problem = _bad_checkpoint(kind, tmp_path / "bad.pt")
    image = tmp_path / "im.png"
    from PIL import Image

    Image.fromarray(np.zeros((8, 8, 3), np.uint8)).save(image)
    out = tmp_path / "o"
    _bad_input(capsys, "recovery", ["evaluate", str(ck), str(dataset), "--out", str(out)], tmp_path, ck, problem)
    _bad_input(capsys, "recovery", ["predict", str(ck), str(image), "--out", str(out)], tmp_path, ck, problem)
    _bad_input(capsys, "recovery", ["export", str(ck), "--out", str(tmp_path / "e.pt")], tmp_path, ck, problem)


def _bad_image(kind: str, dst: Path) -> tuple[Path, str]:
    from PIL import Image

    if kind == "zero_byte":
        dst.write_bytes(b"")
    elif kind == "random_bytes":
        dst.write_bytes(np.random.default_rng(5).bytes(3000))
    elif kind == "truncated":
        buf = io.BytesIO()
        Image.fromarray(np.random.default_rng(6).integers(0, 255, (64, 64, 3), dtype=np.uint8)).save(buf, "PNG")
        dst.write_bytes(buf.getvalue()[:2000])
    elif kind == "folder":
        dst.mkdir()
        return dst, "no such image"
    elif kind == "huge":  # a valid header claiming 100000 x 100000 pixels: refused before decoding
        buf = io.BytesIO()
        Image.new("L", (1, 1)).save(buf, "PNG")
        raw = bytearray(buf.getvalue())
        import zlib

        raw[16:24] = (100000).to_bytes(4, "big") * 2
        raw[29:33] = zlib.crc32(bytes(raw[12:29])).to_bytes(4, "big")
        dst.write_bytes(bytes(raw))
        return dst, "image"
    else:
        raise AssertionError(kind)
    return dst, "not a readable image"


@pytest.mark.parametrize("kind", ["zero_byte", "random_bytes", "truncated", "folder", "huge"])
def test_recovery_predict_bad_images(tmp_path, capsys, kind):
    image, problem = _bad_image(kind, tmp_path / "im.png")
    if kind == "folder":  # recovery predict reads folders of images since 2026-12-06: this one is empty
        problem = "empty folder"
    _bad_input(capsys, "recovery", ["predict", "default", str(image), "--out", str(tmp_path / "o")], tmp_path, image, problem)


def test_recovery_predict_a_one_pixel_image(tmp_path, capsys):
    """A 1 x 1 image is an image: the detector finds nobody in it (listed, no error), and with
    --whole it is predicted like any other (the crop is its padded square)."""
    import json

    from PIL import Image

    image = tmp_path / "px.png"
    Image.new("RGB", (1, 1), (120, 80, 60)).save(image)
    rc, _, err = _run(capsys, "recovery", ["predict", "default", str(image), "--out", str(tmp_path / "o")])
    assert rc == 0, err
    assert sorted(p.name for p in (tmp_path / "o").iterdir()) == ["people.json", "px_overlay.png"]
    assert [e["people"] for e in json.loads((tmp_path / "o" / "people.json").read_text())["images"]] == [[]]
    rc, _, err = _run(capsys, "recovery", ["predict", "default", str(image), "--whole", "--out", str(tmp_path / "w")])
    assert rc == 0, err
    assert sorted(p.name for p in (tmp_path / "w").iterdir()) == ["mesh.obj", "overlay.png", "params.json"]


# A malformed training config per program: (file bytes, or None for a folder / a missing file; the problem)
TRAIN_CONFIGS = {
    "recovery": {
        "unknown_key": (b"optim: {learning_rate: 0.1}\n", "learning_rate"),
        "not_utf8": (b"\xff\xfe optim: {lr: 0.1}\n", "UTF-8"),
        "not_yaml": (b"optim: [1, 2\n", "YAML"),
        "not_a_mapping": (b"- 1\n- 2\n", ""),
        "folder": (None, ""),
    },
    "blsm train": {
        "unknown_key": (b"regsiter: {}\n", "regsiter: unknown key"),
        "not_utf8": (b"seed: 1 # \xe9\n", "not UTF-8 text"),
        "not_yaml": (b"seed: [1\n", "not valid YAML"),
        "not_a_mapping": (b"- 1\n", "expected a mapping"),
        "missing": (None, "cannot read train config"),
        "wrong_type": (b"run: 5\n", "run"),
    },
}


@pytest.mark.parametrize("prog, kind", [(p, k) for p, kinds in TRAIN_CONFIGS.items() for k in kinds])
def test_train_commands_bad_configs(tmp_path, capsys, prog, kind):
    cfg = tmp_path / "c.yaml"
    data, problem = TRAIN_CONFIGS[prog][kind]
    if data is not None:
        cfg.write_bytes(data)
    elif kind == "folder":
        cfg.mkdir()
    out = tmp_path / ("run" if prog == "recovery" else "m.npz")
    _bad_input(capsys, prog, ["train", str(cfg), "--out", str(out)], tmp_path, cfg, problem)


@pytest.mark.parametrize("kind", ["empty_folder", "garbage_manifest", "flipped_png_byte", "truncated_tar"])
def test_recovery_evaluate_bad_datasets(dataset, tmp_path, capsys, kind):
    root = tmp_path / "ds"
    if kind == "empty_folder":
        root.mkdir()
        needle = root / "manifest.json"
    elif kind == "garbage_manifest":
        shutil.copytree(dataset, root)
        _manifest(root, "garbage")
        needle = root / "manifest.json"
    else:
        shutil.copytree(dataset, root)
        needle = _damage(root, kind)[0]
    _bad_input(capsys, "recovery", ["evaluate", "default", str(root), "--out", str(tmp_path / "e")], tmp_path, needle)
    _bad_input(capsys, "recovery", ["cache", str(root), "--out", str(tmp_path / "c")], tmp_path, needle)


# ------------------------------------------------------------------------------------------------
# blsm register and blsm train: scans, landmarks and configs


def _sphere_scan(folder: Path, landmarks: bytes | None) -> Path:
    """``folder/scan.ply`` (an icosphere) and, unless None, its ``scan.landmarks.json``."""
    import trimesh

    scan = folder / "scan.ply"
    trimesh.creation.icosphere(subdivisions=1).export(scan)
    if landmarks is not None:
        (folder / "scan.landmarks.json").write_bytes(landmarks)
    return scan


def _bad_scan(kind: str, folder: Path) -> tuple[Path, list[str], str]:
    """A malformed scan (or its landmarks / register config): the path to name, extra args, the problem."""
    scan = folder / "scan.npz"
    if kind == "zero_byte_npz":
        scan.write_bytes(b"")
        return scan, [], "not a readable .npz scan file"
    if kind == "garbage_npz":
        scan.write_bytes(np.random.default_rng(7).bytes(2000))
        return scan, [], "not a readable .npz scan file"
    if kind == "npz_of_something_else":
        np.savez(scan, weights=np.zeros(3))
        return scan, [], "scan"
    if kind == "garbage_ply":
        scan = folder / "scan.ply"
        scan.write_bytes(np.random.default_rng(8).bytes(2000))
        return scan, [], "mesh"
    if kind == "mesh_without_landmarks":
        return _sphere_scan(folder, None), [], "no landmarks located and no vertex colours"
    landmarks = {"landmarks_not_json": b"{\xff", "landmarks_nan": b'{"nose": [0, NaN, 0]}',
                 "landmarks_unknown_name": b'{"third_eye": [0, 1, 0]}', "register_config_unknown_key": b"{}"}
    problems = {"landmarks_not_json": "landmarks", "landmarks_nan": "landmark 'nose' holds NaN or inf",
                "landmarks_unknown_name": "unknown landmark names ['third_eye']"}
    if kind in problems:
        _sphere_scan(folder, landmarks[kind])
        return folder / "scan.landmarks.json", [], problems[kind]
    if kind == "register_config_unknown_key":
        _sphere_scan(folder, landmarks[kind])
        cfg = folder / "register.yaml"
        cfg.write_text("iterationz: 3\n")
        return cfg, ["--config", str(cfg)], "iterationz"
    raise AssertionError(kind)


REGISTER_DAMAGE = ["zero_byte_npz", "garbage_npz", "npz_of_something_else", "garbage_ply", "mesh_without_landmarks",
                   "landmarks_not_json", "landmarks_nan", "landmarks_unknown_name",
                   "register_config_unknown_key"]


@pytest.mark.parametrize("kind", REGISTER_DAMAGE)
def test_blsm_register_bad_scans(tmp_path, capsys, kind):
    src = tmp_path / "scans"
    src.mkdir()
    bad, extra, problem = _bad_scan(kind, src)
    scans = sorted(str(p) for p in src.iterdir() if p.name.startswith("scan.") and p.suffix in (".npz", ".ply"))
    _bad_input(capsys, "blsm register", ["register", *scans, "--out", str(tmp_path / "reg"), *extra], tmp_path, bad, problem)
