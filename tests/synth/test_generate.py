"""The generator end to end on tiny datasets: validation, determinism, resume after SIGKILL, the
three pipelines, skip-bad, and one-line errors for bad input."""

from __future__ import annotations

import dataclasses
import json
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from tiny_run import TINY, TINY_YAML
from tiny_run import copy_subjects as _copy_subjects
from tiny_run import shard_digests as _shard_digests

from synth.config import BackgroundConfig, HairConfig, OutputConfig
from synth.dataset import format as fmt
from synth.dataset.shards import read_shard, write_shard
from synth.generate import generate
from synth.validate import validate

ROOT = Path(__file__).resolve().parents[2]
HDRI = ROOT.parent / "shared" / "assets" / "hdri"

def test_tiny_dataset_is_complete_and_validates(tiny):
    man = json.loads((tiny / "manifest.json").read_text())
    assert man["complete"] and man["num_samples"] == 6 and len(man["shards"]) == 2
    rep = validate(tiny)
    assert rep.samples == 6 and rep.failures == []
    sample = fmt.decode_sample(read_shard(tiny / "shard-000000.tar")["000000000"])
    doc = sample["json"]
    assert set(read_shard(tiny / "shard-000000.tar")["000000000"]) == set(fmt.FIELDS)
    p = doc["people"][0]
    assert len(p["keypoints_2d"]) == len(doc["keypoint_names"]) == 44
    assert len(p["blsm"]["pose"]) == 47 and len(p["bone_lengths"]) == 20
    assert sample["mask"].max() == len(doc["people"]) and sample["depth"].max() > 0


def _rewrite(tiny: Path, tmp_path: Path, edit) -> Path:
    """A copy of the dataset with sample 0 edited and the manifest checksum updated."""
    out = tmp_path / "edited"
    shutil.copytree(tiny, out)
    path = out / "shard-000000.tar"
    samples = read_shard(path)
    edit(samples["000000000"])
    digest = write_shard(path, [(int(k), v) for k, v in sorted(samples.items())])
    man = json.loads((out / "manifest.json").read_text())
    man["shards"]["shard-000000.tar"]["sha256"] = digest
    (out / "manifest.json").write_text(json.dumps(man))
    return out


def _edit_json(fields, fn):
    doc = json.loads(fields["json"])
    fn(doc)
    fields["json"] = fmt.encode_json(doc)


@pytest.mark.parametrize(
    "what, message",
    [
        ("keypoints", "keypoints_2d are not the projection"),
        ("mask", "the mask differs from the projected meshes"),
        ("box", "is not the mask's box"),
        ("visible", "a visible keypoint lies outside the person's mask"),
        ("pose", "keypoints_3d differ from the rebuilt body"),
        ("depth", "depth differs from the correspondences"),
        ("hair", "correspondences reproject"),
    ],
)
def test_validate_catches_labels_that_disagree_with_the_pixels(tiny, tmp_path, what, message):
    def edit(fields):
        if what == "keypoints":
            _edit_json(fields, lambda d: d["people"][0]["keypoints_2d"][3].__setitem__(0, d["people"][0]["keypoints_2d"][3][0] + 0.5))
        elif what == "mask":
            m = fmt.decode_png(fields["mask.png"])
            fields["mask.png"] = fmt.encode_png(np.roll(m, 3, axis=1))
        elif what == "box":
            _edit_json(fields, lambda d: d["people"][0]["box"].__setitem__(2, d["people"][0]["box"][2] + 1))
        elif what == "visible":
            _edit_json(fields, lambda d: (d["people"][0]["visible"].__setitem__(0, True), d["people"][0]["in_frame"].__setitem__(0, True), d["people"][0]["keypoints_2d"].__setitem__(0, [0.5, 0.5])))
        elif what == "pose":
            _edit_json(fields, lambda d: d["people"][0]["blsm"]["pose"].__setitem__(20, d["people"][0]["blsm"]["pose"][20] + 0.5))
        elif what == "hair":  # another hair than the one rendered
            _edit_json(fields, lambda d: d["people"][0]["hair"].__setitem__("length", d["people"][0]["hair"]["length"] * 1.5))
        elif what == "depth":
            dep = fmt.decode_exr(fields["depth.exr"])
            fields["depth.exr"] = fmt.encode_exr(np.where(dep > 0, dep + 0.01, 0).astype(np.float32))

    rep = validate(_rewrite(tiny, tmp_path, edit))
    assert any(message in f for f in rep.failures), rep.failures


def _hair_pixels(dataset: Path) -> tuple[int, int, set[str]]:
    """(hair pixels, of them on the head part, styles) over a dataset's first shard."""
    from synth.subjects import load_subject

    n = on_head = 0
    styles = set()
    for fields in read_shard(dataset / "shard-000000.tar").values():
        s = fmt.decode_sample(fields)
        doc = s["json"]
        head = doc["part_names"].index("head") + 1
        for i, p in enumerate(doc["people"]):
            faces = len(load_subject(dataset / "subjects" / f"{p['subject']}.npz").faces)
            hair = (s["mask"] == i + 1) & (s["corr"][..., 0] >= faces)
            n += int(hair.sum())
            on_head += int((s["parts"][hair] == head).sum())
            if "hair" in p:
                styles.add(p["hair"]["style"])
    return n, on_head, styles


def test_hair_is_in_the_mask_on_the_head_and_off_when_asked(tiny, tmp_path):
    from synth.hair import STYLES

    n, on_head, styles = _hair_pixels(tiny)
    assert n > 0 and on_head == n and styles and styles <= set(STYLES)
    out = tmp_path / "bald"
    out.mkdir()
    _copy_subjects(tiny, out)
    generate(dataclasses.replace(TINY, num=2, hair=HairConfig(enabled=False)), out, progress=False)
    assert _hair_pixels(out) == (0, 0, set())
    assert validate(out).failures == []


def test_validate_catches_a_damaged_shard_and_exits_nonzero(tiny, tmp_path):
    out = tmp_path / "damaged"
    shutil.copytree(tiny, out)
    data = bytearray((out / "shard-000001.tar").read_bytes())
    data[2000] ^= 0xFF
    (out / "shard-000001.tar").write_bytes(bytes(data))
    r = subprocess.run([sys.executable, "-m", "synth.cli", "validate", str(out)], capture_output=True, text=True, cwd=ROOT)
    assert r.returncode == 1
    assert "SHA-256 differs from the manifest" in r.stdout


def test_sigkill_then_resume_gives_the_same_dataset(tiny, tmp_path):
    """A run killed with SIGKILL part-way and resumed equals the uninterrupted run, byte for byte
    on this dataset (labels always; the RGB can differ in a rare pixel, see README)."""
    # One image per shard, so that the kill lands between shards however fast images are made.
    ref = tmp_path / "uninterrupted"
    ref.mkdir()
    _copy_subjects(tiny, ref)
    generate(dataclasses.replace(TINY, output=OutputConfig(shard_size=1)), ref, progress=False)
    cfg = tmp_path / "tiny.yaml"
    cfg.write_text(TINY_YAML.replace("output: {shard_size: 3}", "output: {shard_size: 1}"))
    out = tmp_path / "killed"
    out.mkdir()
    _copy_subjects(tiny, out)
    cmd = [sys.executable, "-m", "synth.cli", "generate", str(cfg), "--out", str(out)]
    proc = subprocess.Popen(cmd, cwd=ROOT, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    deadline = time.time() + 300
    # The manifest is rewritten after each shard; waiting for it (not for the first tar) kills the
    # run after a shard and its manifest entry exist.
    while not (out / "manifest.json").exists() and time.time() < deadline and proc.poll() is None:
        time.sleep(0.01)
    assert proc.poll() is None, "the run ended before it could be killed"
    os.kill(proc.pid, signal.SIGKILL)
    proc.wait()
    names = [f"shard-{i:06d}.tar" for i in range(TINY.num)]
    assert not all((out / n).exists() for n in names)
    man = json.loads((out / "manifest.json").read_text())
    assert not man["complete"]
    r = subprocess.run(cmd + ["--resume"], cwd=ROOT, capture_output=True, text=True)
    assert r.returncode == 0, r.stderr
    for name in names:
        a, b = read_shard(out / name), read_shard(ref / name)
        assert a.keys() == b.keys()
        differ = [f"{k}.{f}" for k in a for f in a[k] if a[k][f] != b[k][f]]
        assert not differ, f"{name}: members differ: {differ}"
    assert _shard_digests(out) == _shard_digests(ref)
    for name in names:
        assert (out / name).read_bytes() == (ref / name).read_bytes()


def test_two_workers_make_the_same_bytes_as_one(tiny, tmp_path):
    """Samples depend on (seed, index) only: on this dataset, worker and thread counts do not change
    a byte (labels never change; the RGB can differ in a rare pixel with history, see README)."""
    out = tmp_path / "two"
    out.mkdir()
    _copy_subjects(tiny, out)
    man = generate(TINY, out, workers=2, progress=False)
    assert man["complete"] and _shard_digests(out) == _shard_digests(tiny)


@pytest.mark.parametrize("pipeline", ["raw", "blsm"])
def test_raw_and_blsm_pipelines_validate(tiny, tmp_path, pipeline):
    out = tmp_path / pipeline
    out.mkdir()
    _copy_subjects(tiny, out)
    cfg = dataclasses.replace(TINY, num=3, pipeline=pipeline, subdivide=pipeline == "blsm")
    generate(cfg, out, progress=False)
    rep = validate(out)
    assert rep.samples == 3 and rep.failures == []
    doc = fmt.decode_sample(read_shard(out / "shard-000000.tar")["000000000"])["json"]
    assert doc["people"][0]["pipeline"] == pipeline


@pytest.mark.skipif(not HDRI.is_dir(), reason="needs ../shared/assets/hdri (the shared CC0 HDRIs)")
def test_hdri_backgrounds_validate(tiny, tmp_path):
    out = tmp_path / "hdri"
    out.mkdir()
    _copy_subjects(tiny, out)
    cfg = dataclasses.replace(TINY, num=2, background=BackgroundConfig(kind="hdri", folder=str(HDRI), env_width=256))
    generate(cfg, out, progress=False)
    assert validate(out).failures == []
    doc = fmt.decode_sample(read_shard(out / "shard-000000.tar")["000000000"])["json"]
    assert doc["background"]["kind"] == "hdri" and doc["background"]["file"].endswith(".exr")


def test_a_new_background_kind_is_one_file_and_one_registration_line(tiny, tmp_path, monkeypatch):
    """What adding a background kind costs (issue 54): its module (the class below) and one line of
    ``synth.backgrounds.KINDS``; then the config accepts it, a run checks, draws and records it, and
    ``synth validate`` passes, with nothing else edited."""
    from synth.backgrounds import KINDS, Background
    from synth.backgrounds.sky import procedural_sky

    class Grey:  # the new file's content: a plain grey backdrop, the people lit by the procedural sky
        name, needs_folder, follows_cameras = "grey", False, True

        def check(self, cfg):
            pass

        def open(self, cfg):
            return None

        def draw(self, state, cfg, rng, camera, size, rotation, scale):
            env, info = procedural_sky(cfg.env_width, rng)
            level = float(rng.uniform(0.1, 0.5))
            plate = np.full((size[1], size[0], 3), level, np.float32)
            return Background("grey", env, rotation, scale, plate, {"level": level, "rotation": rotation, "exposure": scale})

        def records(self, cfg):
            return set()

    with pytest.raises(ValueError, match="background.kind must be one of default, hdri, images, got 'grey'"):
        BackgroundConfig(kind="grey")
    monkeypatch.setitem(KINDS, "grey", Grey())  # the registration line
    out = tmp_path / "grey"
    out.mkdir()
    _copy_subjects(tiny, out)
    generate(dataclasses.replace(TINY, num=2, background=BackgroundConfig(kind="grey", env_width=256)), out, progress=False)
    assert validate(out).failures == []
    sample = fmt.decode_sample(read_shard(out / "shard-000000.tar")["000000000"])
    assert sample["json"]["background"]["kind"] == "grey" and 0.1 <= sample["json"]["background"]["level"] <= 0.5
    behind = sample["rgb"][sample["mask"] == 0].astype(int)  # the backdrop's pixels: grey, but where
    # the people's edges blend in (coverage under one mask pixel) and the lens' effects reach
    spread = behind.max(1) - behind.min(1)
    assert len(behind) > 1000 and np.percentile(spread, 90) <= 3, np.percentile(spread, [50, 90, 99])


def _plates(folder: Path, describe: bool) -> Path:
    """Two backplates, sky blue above 45 % of the height and grass green below; with ``describe``
    their plates.json gives that horizon."""
    from PIL import Image

    folder.mkdir()
    for name, (w, h) in (("a.png", (240, 160)), ("b.png", (200, 200))):
        img = np.zeros((h, w, 3), np.uint8)
        img[: int(0.45 * h)] = (90, 150, 230)
        img[int(0.45 * h):] = (40, 170, 40)
        Image.fromarray(img).save(folder / name)
    if describe:
        (folder / "plates.json").write_text(json.dumps({"a.png": {"horizon": 0.45}, "b.png": {"horizon": 0.45}}))
    return folder


def test_backplates_meet_the_cameras_horizon(tiny, tmp_path):
    from synth.backgrounds import plates as bg

    cfg = dataclasses.replace(TINY, num=4, camera=dataclasses.replace(TINY.camera, rare_rate=0.0, truncation_rate=0.0),
                              background=BackgroundConfig(kind="images", folder=str(_plates(tmp_path / "plates", True))))
    out = tmp_path / "aligned"
    out.mkdir()
    _copy_subjects(tiny, out)
    generate(cfg, out, progress=False)
    assert validate(out).failures == []
    aligned = 0
    for key, sample in sorted(read_shard(out / "shard-000000.tar").items()):
        doc = fmt.decode_sample(sample)
        row = doc["json"]["background"]["horizon_row"]
        if row is None:
            continue
        aligned += 1
        cam = doc["json"]["camera"]
        K, R = np.asarray(cam["K"]), np.asarray(cam["R"])
        # K, R and the row are stored rounded to 1e-6 (synth.dataset.format.json_round): the row recomputed
        # from them agrees to the rounding's first-order bound, v = cy - fy R21 / R11, not better
        ratio = R[2, 1] / R[1, 1]
        bound = 5e-7 * (2 + abs(ratio) + abs(K[1, 1]) * (1 + abs(ratio)) / abs(R[1, 1]))
        assert abs(row - bg.horizon_row(K, R)) <= 1.01 * bound + 1e-9
        rgb, mask = doc["rgb"][..., :3].astype(float), doc["mask"] > 0
        r = int(round(row))
        if 2 <= r <= rgb.shape[0] - 3:  # sky (blue) just above the horizon, grass (green) below, beside the people
            above, below = rgb[r - 2][~mask[r - 2]], rgb[r + 2][~mask[r + 2]]
            assert (above[:, 2] > above[:, 1]).mean() > 0.9 and (below[:, 1] > below[:, 2]).mean() > 0.9, key
    assert aligned >= 3
    # off, or a folder without plates.json: the backplate path of before, the same bytes
    plain = tmp_path / "plain"
    plain.mkdir()
    _copy_subjects(tiny, plain)
    generate(dataclasses.replace(cfg, background=BackgroundConfig(kind="images", folder=str(_plates(tmp_path / "p2", False)))),
             plain, progress=False)
    off = tmp_path / "off"
    off.mkdir()
    _copy_subjects(tiny, off)
    generate(dataclasses.replace(cfg, background=dataclasses.replace(cfg.background, align_horizon=False)), off, progress=False)
    assert _shard_digests(off) == _shard_digests(plain)
    # the labels never depend on the plate
    for k, sample in read_shard(out / "shard-000000.tar").items():
        a, b = fmt.decode_sample(sample)["json"], fmt.decode_sample(read_shard(off / "shard-000000.tar")[k])["json"]
        assert a["people"] == b["people"] and a["camera"] == b["camera"]


def test_skip_bad_lists_the_failing_sample_and_keeps_the_others(tiny, tmp_path, monkeypatch):
    from synth import sample as gen

    real = gen.SampleMaker.make

    def flaky(self, index, rng):
        if index == 1:
            raise RuntimeError("simulated failure")
        return real(self, index, rng)

    monkeypatch.setattr(gen.SampleMaker, "make", flaky)
    out = tmp_path / "skip"
    out.mkdir()
    _copy_subjects(tiny, out)
    with pytest.raises(RuntimeError, match="sample 1: simulated failure"):
        generate(dataclasses.replace(TINY, num=3), out, progress=False)
    assert not list(out.glob("shard-*.tar")) and not list(out.glob(".shard-*"))  # no partial shard
    shutil.rmtree(out)
    out.mkdir()
    _copy_subjects(tiny, out)
    man = generate(dataclasses.replace(TINY, num=3, skip_bad=True), out, progress=False)
    assert man["skipped"] == [{"index": 1, "reason": "RuntimeError: simulated failure"}]
    assert sorted(read_shard(out / "shard-000000.tar")) == ["000000000", "000000002"]


def _cli(args, cwd=ROOT):
    return subprocess.run([sys.executable, "-m", "synth.cli", *args], capture_output=True, text=True, cwd=cwd)


def test_bad_input_is_one_line_naming_the_file_and_writes_nothing(tiny, tmp_path):
    bad = tmp_path / "bad.yaml"
    bad.write_text("nmu: 3\n")
    r = _cli(["generate", str(bad), "--out", str(tmp_path / "o1")])
    assert r.returncode == 2 and r.stderr.strip().count("\n") == 0
    assert r.stderr.startswith(f"synth: error: {bad}: nmu: unknown key")
    assert not (tmp_path / "o1").exists()

    empty = tmp_path / "empty_hdri"
    empty.mkdir()
    cfg = tmp_path / "c.yaml"
    cfg.write_text(TINY_YAML + f"background: {{kind: hdri, folder: {empty}}}\n".replace("background: {env_width: 128}\n", ""))
    cfg.write_text(TINY_YAML.replace("background: {env_width: 128}", f"background: {{kind: hdri, folder: {empty}}}"))
    out = tmp_path / "o2"
    out.mkdir()
    _copy_subjects(tiny, out)
    r = _cli(["generate", str(cfg), "--out", str(out)])
    assert r.returncode == 2 and r.stderr.strip().count("\n") == 0, r.stderr
    assert f"{empty}: the HDRI folder holds no" in r.stderr
    assert not list(out.glob("shard-*.tar"))

    # A subject file with NaN vertices: the error names the file.
    out3 = tmp_path / "o3"
    out3.mkdir()
    _copy_subjects(tiny, out3)
    p = out3 / "subjects" / "anny_0000.npz"
    with np.load(p) as z:
        arrays = {k: z[k] for k in z.files}
    arrays["vertices"][5, 1] = np.nan
    np.savez(p, **arrays)
    cfg3 = tmp_path / "c3.yaml"
    cfg3.write_text(TINY_YAML)
    r = _cli(["generate", str(cfg3), "--out", str(out3)])
    assert r.returncode == 2 and f"{p}: vertices has NaN or inf" in r.stderr, r.stderr
    assert not list(out3.glob("shard-*.tar"))

    # Subjects made with another seed (or model, or texture size) are not silently reused: a
    # resumed run would otherwise not be the dataset an uninterrupted run makes.
    out4 = tmp_path / "o4"
    out4.mkdir()
    _copy_subjects(tiny, out4)
    cfg4 = tmp_path / "c4.yaml"
    cfg4.write_text(TINY_YAML.replace("seed: 7", "seed: 8"))
    r = _cli(["generate", str(cfg4), "--out", str(out4)])
    p4 = out4 / "subjects" / "anny_0000.npz"
    assert r.returncode == 2 and r.stderr.strip().count("\n") == 0, r.stderr
    assert f"{p4}: subject made with other settings (seed differs)" in r.stderr, r.stderr
    assert not list(out4.glob("shard-*.tar"))
