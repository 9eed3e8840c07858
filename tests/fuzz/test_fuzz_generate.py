"""Fuzz corpus for ``synth generate`` (issue 17): malformed configs, background files, scan folders,
a second writer, a full disk; and the validator's keypoint tolerance.

Every malformed-input case holds the README's contract: exit status 2, exactly one line on stderr
(``synth: error: <path>: <problem>``, file descriptor 2 included, so that a C library's own error
print counts), no traceback, and no new file or folder anywhere under the test's folder. The CLI
runs in this process; runs that need samples use the fakes of ``tests/synth/fakes.py`` in place of
subjects and Mitsuba (the shard writer, manifest, lock and resume logic are the real ones).
"""

from __future__ import annotations

import json
import os
import socket
import struct
import subprocess
import sys
import zlib
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "synth"))
import fakes  # noqa: E402

from blsm.camera import Camera  # noqa: E402
from synth import lock as out_lock  # noqa: E402
from synth.cli import main  # noqa: E402
from synth.dataset import format as fmt  # noqa: E402
from synth.validate import check_keypoints  # noqa: E402

SIZE = 64
FAKE_YAML = f"seed: 3\nnum: 4\ncamera: {{width: {SIZE}, height: {SIZE}}}\noutput: {{shard_size: 2}}\n"


# ------------------------------------------------------------------------------------------------
# Helpers


def snapshot(root: Path) -> set[str]:
    return {str(p.relative_to(root)) for p in root.rglob("*")}


def run(capfd, *args: str) -> tuple[int, str]:
    capfd.readouterr()
    rc = main([str(a) for a in args])
    return rc, capfd.readouterr().err


def assert_refused(rc: int, err: str, path: Path | str, problem: str, before: set[str] | None = None, root: Path | None = None) -> None:
    lines = err.splitlines()
    assert rc == 2, (rc, err)
    assert len(lines) == 1, err
    assert "Traceback" not in err
    assert lines[0].startswith(f"synth: error: {path}"), err
    assert problem in lines[0], err
    if before is not None:
        assert snapshot(root) == before, sorted(snapshot(root) ^ before)


@pytest.fixture(autouse=True)
def quick(model, monkeypatch):
    """The session's model for every ``blsm.load()``; one thread (the machine is shared)."""
    import torch

    import blsm

    monkeypatch.setattr(blsm, "load", lambda *a, **k: model)
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)


def write_exr(path: Path, rgb: np.ndarray) -> Path:
    import OpenImageIO as oiio

    rgb = np.ascontiguousarray(rgb, np.float32)
    spec = oiio.ImageSpec(rgb.shape[1], rgb.shape[0], 3, "half")
    out = oiio.ImageOutput.create(str(path))
    assert out.open(str(path), spec)
    out.write_image(rgb)
    out.close()
    return path


def write_png(path: Path, h: int = 48, w: int = 64) -> Path:
    from PIL import Image

    rng = np.random.default_rng(0)
    Image.fromarray(rng.integers(0, 255, (h, w, 3), dtype=np.uint8)).save(path)
    return path


def huge_png(path: Path) -> Path:
    """A valid small PNG whose header claims 20000 x 20000 pixels (a decompression bomb)."""
    data = bytearray(write_png(path).read_bytes())
    ihdr = data.index(b"IHDR")
    data[ihdr + 4 : ihdr + 12] = struct.pack(">II", 20_000, 20_000)
    data[ihdr + 17 : ihdr + 21] = struct.pack(">I", zlib.crc32(bytes(data[ihdr : ihdr + 17])))
    path.write_bytes(bytes(data))
    return path


def good_hdri(path: Path) -> Path:
    return write_exr(path, np.full((32, 64, 3), 0.5, np.float32))


# ------------------------------------------------------------------------------------------------
# Configs


CONFIGS = [
    ("non_utf8_utf16", "\ufeffseed: 1\n".encode("utf-16"), "not UTF-8 text (byte 0xff at offset 0"),
    ("non_utf8_latin1", "seed: 1  # café\n".encode("latin-1"), "not UTF-8 text (byte 0xe9"),
    ("bom_then_unknown_key", b"\xef\xbb\xbfnmu: 3\n", "nmu: unknown key"),
    ("binary_garbage", b"\x00\x01\x02\x03seed", "not valid YAML"),
    ("bad_yaml", b"seed: [\n", "not valid YAML"),
    ("a_list", b"[1, 2]\n", "(top level): expected a mapping, got list"),
    ("a_scalar", b"42\n", "(top level): expected a mapping, got int"),
    ("unknown_top_key", b"sed: 3\n", "sed: unknown key"),
    ("unknown_nested_key", b"camera: {widht: 64}\n", "camera.widht: unknown key"),
    ("wrong_type_int", b"num: ten\n", "num: expected an integer, got 'ten'"),
    ("wrong_type_bool", b"subdivide: 3\n", "subdivide: expected true or false"),
    ("wrong_type_section", b"render: 16\n", "render: expected a mapping"),
    ("nan", b"camera: {rare_rate: .nan}\n", "camera.rare_rate: expected a finite number"),
    ("huge_image", b"camera: {width: 100000, height: 100000}\n", "over the limit of 8192 px a side"),
    ("huge_memory", b"camera: {width: 8192, height: 8192}\nrender: {spp: 64}\n", "GiB per worker, over the limit of 32 GiB"),
    ("huge_num", b"num: 1000000000000\n", "num (the number of images) must be at most 1000000000"),
]


@pytest.mark.parametrize("name, data, problem", CONFIGS, ids=[c[0] for c in CONFIGS])
def test_bad_config_is_one_line_and_writes_nothing(tmp_path, capfd, name, data, problem):
    cfg = tmp_path / "bad.yaml"
    cfg.write_bytes(data)
    before = snapshot(tmp_path)
    rc, err = run(capfd, "generate", cfg, "--out", tmp_path / "out")
    assert_refused(rc, err, cfg, problem, before, tmp_path)


@pytest.mark.parametrize("kind", ["directory", "missing"])
def test_unreadable_config_path(tmp_path, capfd, kind):
    cfg = tmp_path / "cfg.yaml"
    if kind == "directory":
        cfg.mkdir()
    before = snapshot(tmp_path)
    rc, err = run(capfd, "generate", cfg, "--out", tmp_path / "out")
    assert_refused(rc, err, cfg, "cannot read config", before, tmp_path)


def test_bom_and_empty_configs_are_accepted(tmp_path):
    """Documented: a UTF-8 byte-order mark is not content, and an empty file is the defaults."""
    from synth.config import GeneratorConfig, load_config

    p = tmp_path / "c.yaml"
    p.write_bytes(b"\xef\xbb\xbfseed: 5\n")
    assert load_config(p).seed == 5
    p.write_bytes(b"")
    assert load_config(p) == GeneratorConfig()


# ------------------------------------------------------------------------------------------------
# Backgrounds: every file opened and decoded before any work


def _hdri_case(folder: Path, case: str) -> tuple[Path, str]:
    folder.mkdir()
    good_hdri(folder / "a_good.exr")
    bad = folder / "bad.exr"
    if case == "zero_byte":
        bad.write_bytes(b"")
        return bad, "empty file (0 bytes)"
    if case == "truncated":
        data = write_exr(bad, np.random.default_rng(1).uniform(0.1, 2.0, (64, 128, 3))).read_bytes()
        bad.write_bytes(data[: len(data) * 2 // 3])
        return bad, "corrupt or truncated image"
    if case == "random_bytes":
        bad.write_bytes(np.random.default_rng(2).bytes(4096))
        return bad, "not a readable image"
    if case == "one_pixel":
        write_exr(bad, np.ones((1, 1, 3)))
        return bad, "image is 1x1 px, under the minimum of 16 px a side"
    if case == "black":
        write_exr(bad, np.zeros((32, 64, 3)))
        return bad, "the environment map is black"
    if case == "nan":
        px = np.ones((32, 64, 3), np.float32)
        px[3, 4, 1] = np.nan
        write_exr(bad, px)
        return bad, "NaN or inf pixels"
    if case == "text_as_hdr":
        bad = folder / "bad.hdr"
        bad.write_text("#?RADIANCE\nFORMAT=32-bit_rle_rgbe\n\n-Y 16 +X 32\n")  # header, no pixels
        return bad, "image"
    raise AssertionError(case)


def _generate_with(tmp_path: Path, capfd, background: str, extra: str = "") -> tuple[int, str, set[str]]:
    cfg = tmp_path / "cfg.yaml"
    cfg.write_text(FAKE_YAML + f"background: {background}\n" + extra)
    before = snapshot(tmp_path)
    rc, err = run(capfd, "generate", cfg, "--out", tmp_path / "out")
    return rc, err, before


HDRI_CASES = ["zero_byte", "truncated", "random_bytes", "one_pixel", "black", "nan", "text_as_hdr"]


@pytest.mark.parametrize("case", HDRI_CASES)
def test_bad_hdri_file_is_found_before_any_work(tmp_path, capfd, fake_run, case):
    bad, problem = _hdri_case(tmp_path / "hdri", case)
    rc, err, before = _generate_with(tmp_path, capfd, f"{{kind: hdri, folder: {tmp_path / 'hdri'}, env_width: 64}}")
    assert_refused(rc, err, bad, problem, before, tmp_path)


@pytest.mark.parametrize("case", ["zero_byte", "truncated", "random_bytes", "one_pixel", "huge_header", "over_pixel_limit"])
def test_bad_backplate_is_found_before_any_work(tmp_path, capfd, fake_run, monkeypatch, case):
    folder = tmp_path / "plates"
    folder.mkdir()
    write_png(folder / "a_good.png")
    bad = folder / ("bad.jpg" if case == "random_bytes" else "bad.png")
    if case == "zero_byte":
        bad.write_bytes(b"")
        problem = "empty file (0 bytes)"
    elif case == "truncated":
        data = write_png(bad, 96, 128).read_bytes()
        bad.write_bytes(data[: len(data) // 2])
        problem = "corrupt or truncated image"
    elif case == "random_bytes":
        bad.write_bytes(np.random.default_rng(3).bytes(3000))
        problem = "not a readable image"
    elif case == "one_pixel":
        write_png(bad, 1, 1)
        problem = "image is 1x1 px, under the minimum"
    elif case == "huge_header":
        huge_png(bad)
        problem = "png header claims a 1144 MB image"  # OpenImageIO's own guard
    else:
        from synth.backgrounds import files

        monkeypatch.setattr(files, "MAX_PIXELS", 64 * 64 - 1)
        write_png(bad, 64, 64)
        problem = "image is 64x64 px, over the limit of 4095 pixels"
    rc, err, before = _generate_with(tmp_path, capfd, f"{{kind: images, folder: {folder}}}")
    assert_refused(rc, err, bad, problem, before, tmp_path)


@pytest.mark.parametrize("case", ["no_usable_files", "missing_folder", "excluded_all"])
def test_background_folder_without_usable_files(tmp_path, capfd, fake_run, case):
    folder = tmp_path / "hdri"
    extra = ""
    if case != "missing_folder":
        folder.mkdir()
        (folder / "notes.txt").write_text("not an image")
        (folder / "sub.exr").mkdir()  # a folder named like an image
    if case == "excluded_all":
        good_hdri(folder / "only.exr")
        extra = ", exclude: [only.exr]"
    rc, err, before = _generate_with(tmp_path, capfd, f"{{kind: hdri, folder: {folder}{extra}}}")
    problem = "no such HDRI folder" if case == "missing_folder" else "the HDRI folder holds no .exr/.hdr files"
    assert_refused(rc, err, folder, problem, before, tmp_path)


# ------------------------------------------------------------------------------------------------
# Scan folders: every subject folder opened and checked before any work


def _tetra(folder: Path) -> None:
    import trimesh

    folder.mkdir(parents=True, exist_ok=True)
    v = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]], float)
    f = np.array([[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]])
    trimesh.Trimesh(v, f, vertex_colors=np.full((4, 4), 200, np.uint8), process=False).export(folder / "scan.ply")


def _params(model) -> dict[str, np.ndarray]:
    return {
        "bone": np.zeros(model.num_bone_coeffs, np.float32),
        "shape": np.zeros(model.num_shape_coeffs, np.float32),
        "angles": np.zeros(model.num_dofs, np.float32),
        "global_orient": np.zeros(3, np.float32),
        "transl": np.zeros(3, np.float32),
    }


SCAN_CASES = ["empty_root", "missing_root", "no_scan_file", "garbage_scan", "truncated_npz", "wrong_array_shape", "unknown_array", "registration_json_not_utf8", "all_bad_with_skip_bad"]


@pytest.mark.parametrize("case", SCAN_CASES)
def test_bad_scan_folder_is_found_before_any_work(tmp_path, capfd, fake_run, model, case):
    root = tmp_path / "scans"
    sub = root / "person"
    extra = ""
    if case != "missing_root":
        root.mkdir()
    if case not in ("empty_root", "missing_root"):
        _tetra(sub)
        np.savez(sub / "registration.npz", **_params(model))
    bad, problem = sub / "registration.npz", ""
    if case == "empty_root":
        bad, problem = root, "no subject folders"
    elif case == "missing_root":
        bad, problem = root, "no such scans folder"
    elif case == "no_scan_file":
        (sub / "scan.ply").unlink()
        bad, problem = sub, "no scan.obj | scan.ply | scan.glb file"
    elif case == "garbage_scan":
        (sub / "scan.ply").write_bytes(np.random.default_rng(4).bytes(2000))
        bad = sub / "scan.ply"
        problem = "mesh"  # "unreadable mesh (...)" or "empty mesh (no triangles)"
    elif case == "truncated_npz":
        data = bad.read_bytes()
        bad.write_bytes(data[: len(data) // 2])
        problem = "not a readable .npz registration file"
    elif case == "wrong_array_shape":
        np.savez(bad, **{**_params(model), "angles": np.zeros(5, np.float32)})
        problem = "angles"
    elif case == "unknown_array":
        np.savez(bad, **_params(model), colour=np.zeros(3))
        problem = "unknown registration keys ['colour']"
    elif case == "registration_json_not_utf8":
        bad.unlink()
        bad = sub / "registration.json"
        bad.write_bytes(b'{"bone": [\xff]}')
        problem = "unreadable registration JSON"
    elif case == "all_bad_with_skip_bad":
        (sub / "registration.npz").unlink()
        bad, problem = root, "no usable scan"
        extra = "skip_bad: true\n"
    rc, err, before = _generate_with(tmp_path, capfd, "{kind: default}", f"subjects: {{source: folder, folder: {root}}}\n" + extra)
    assert_refused(rc, err, bad, problem, before, tmp_path)


# ------------------------------------------------------------------------------------------------
# Runs with samples: fakes in place of subjects and Mitsuba


class FakeMaker:
    """Stands in for synth.sample.SampleMaker: fake samples (tests/synth/fakes.py), 64 px."""

    hook = None

    def __init__(self, cfg, out, variant, threads=0) -> None:
        import blsm

        self.cfg, self.model = cfg, blsm.load()

    def make(self, index: int, rng: np.random.Generator) -> dict[str, bytes]:
        if FakeMaker.hook is not None:
            FakeMaker.hook(index)
        return fakes.make_sample(index, rng, self.model, (SIZE, SIZE))


@pytest.fixture
def fake_run(monkeypatch):
    from synth import generate as gen
    from synth import worker

    def prepare(cfg, out, model):
        (out / gen.SUBJECTS).mkdir(parents=True, exist_ok=True)
        (out / gen.SUBJECTS / "index.json").write_text('{"subjects": {}, "skipped": []}\n')
        return []

    monkeypatch.setattr(gen, "prepare_subjects", prepare)
    monkeypatch.setattr(gen, "choose_variant", lambda cfg: "scalar_rgb")
    monkeypatch.setattr(gen, "versions", lambda: {"fake": "1"})
    monkeypatch.setattr(worker, "SampleMaker", FakeMaker)
    monkeypatch.setattr(gen, "PoseSource", lambda cfg: None)
    monkeypatch.setattr(FakeMaker, "hook", None)
    return gen


def _config(tmp_path: Path) -> Path:
    cfg = tmp_path / "cfg.yaml"
    cfg.write_text(FAKE_YAML)
    return cfg


def _shards(out: Path) -> dict[str, bytes]:
    return {p.name: p.read_bytes() for p in sorted(out.glob("shard-*.tar"))}


@pytest.fixture
def reference(tmp_path, fake_run, capfd):
    """An undisturbed fake run's shards."""
    out = tmp_path / "reference"
    rc, err = run(capfd, "generate", _config(tmp_path), "--out", out)
    assert rc == 0, err
    assert json.loads((out / "manifest.json").read_text())["complete"]
    assert not list(out.glob(".lock*")) and not list(out.glob(".*.tmp"))
    return _shards(out)


def test_second_writer_is_refused_while_the_first_runs(tmp_path, fake_run, capfd, reference):
    out = tmp_path / "out"
    cfg = _config(tmp_path)
    seen: dict[str, object] = {}

    def second(index: int) -> None:
        if index == 1 and "rc" not in seen:
            before = snapshot(tmp_path)
            capfd.readouterr()
            seen["rc"] = main(["generate", str(cfg), "--out", str(out), "--resume"])
            seen["err"] = capfd.readouterr().err
            seen["same"] = snapshot(tmp_path) == before

    FakeMaker.hook = second
    rc, err = run(capfd, "generate", cfg, "--out", out)
    assert rc == 0, err
    assert_refused(seen["rc"], seen["err"], out, "in use by another synth generate (host")
    assert f"pid {os.getpid()}" in seen["err"] and seen["same"]
    assert _shards(out) == reference  # the first's dataset is whole
    assert not list(out.glob(".lock*"))


def test_held_lock_refuses_with_the_holder_named(tmp_path, fake_run, capfd):
    out = tmp_path / "out"
    out.mkdir()
    cfg = _config(tmp_path)
    with out_lock.acquire(out) as held:
        before = snapshot(tmp_path)
        rc, err = run(capfd, "generate", cfg, "--out", out)
        assert_refused(rc, err, out, f"(host {held.holder['host']}, pid {os.getpid()}, since {held.holder['started']}", before, tmp_path)


def test_lock_left_by_a_dead_process_is_taken_over_with_a_warning(tmp_path, fake_run, capfd, reference):
    out = tmp_path / "out"
    out.mkdir()
    dead = subprocess.Popen([sys.executable, "-c", "pass"])
    dead.wait()
    holder = {"host": socket.gethostname(), "pid": dead.pid, "started": "2026-01-01T00:00:00+00:00", "part": 1, "parts": 1}
    (out / ".lock").write_text(json.dumps(holder))
    stale = out / f".shard-000000.tar.{out_lock.tag_of(holder)}.tmp"
    stale.write_bytes(b"half a shard")
    rc, err = run(capfd, "generate", _config(tmp_path), "--out", out)
    assert rc == 0, err
    warnings = [line for line in err.splitlines() if "taking over the lock" in line]
    assert len(warnings) == 1 and f"pid {dead.pid}" in warnings[0]
    assert not stale.exists() and not (out / ".lock").exists()
    assert _shards(out) == reference


def test_lock_from_another_host_is_refused(tmp_path, fake_run, capfd):
    out = tmp_path / "out"
    out.mkdir()
    (out / ".lock").write_text(json.dumps({"host": "elsewhere.example", "pid": 1, "started": "2026-01-01T00:00:00+00:00"}))
    cfg = _config(tmp_path)
    before = snapshot(tmp_path)
    rc, err = run(capfd, "generate", cfg, "--out", out)
    assert_refused(rc, err, out, "locked by a run on another host (host elsewhere.example, pid 1", before, tmp_path)


def test_part_locks_admit_disjoint_parts_only(tmp_path):
    """The design for ``--part I/N``: parts of one N coexist; the whole run or another N conflicts."""
    with out_lock.acquire(tmp_path, 1, 2), out_lock.acquire(tmp_path, 2, 2):
        assert sorted(p.name for p in tmp_path.glob(".lock*")) == [".lock-part-1-of-2", ".lock-part-2-of-2"]
        for part, parts in ((1, 1), (1, 2), (3, 3)):
            with pytest.raises(ValueError, match="in use by another synth generate"):
                out_lock.acquire(tmp_path, part, parts)
    assert not list(tmp_path.glob(".lock*"))
    with out_lock.acquire(tmp_path), pytest.raises(ValueError, match=r"lock \.lock\)"):
        out_lock.acquire(tmp_path, 2, 2)


def test_temporary_shard_names_carry_the_writer(tmp_path, fake_run, capfd):
    out = tmp_path / "out"
    seen: list[str] = []
    FakeMaker.hook = lambda index: seen.extend(p.name for p in out.glob(".shard-*"))
    rc, err = run(capfd, "generate", _config(tmp_path), "--out", out)
    assert rc == 0, err
    tag = out_lock.tag_of({"host": socket.gethostname(), "pid": os.getpid()})
    assert seen and set(seen) <= {f".shard-00000{s}.tar.{tag}.tmp" for s in range(2)}, seen


class _FullDisk:
    """A file whose writes fail with ENOSPC once ``budget`` bytes are spent."""

    def __init__(self, fh, budget: list[int]) -> None:
        self.fh, self.budget = fh, budget

    def write(self, data) -> int:
        if len(data) > self.budget[0]:
            raise OSError(28, "No space left on device")
        self.budget[0] -= len(data)
        return self.fh.write(data)

    def __getattr__(self, name):
        return getattr(self.fh, name)


@pytest.mark.parametrize("where", ["shard", "manifest"])
def test_full_disk_is_one_line_and_resume_gives_the_same_bytes(tmp_path, fake_run, capfd, reference, monkeypatch, where):
    import contextlib

    from synth.dataset import shards

    real = shards.atomic_write
    calls: dict[str, int] = {}

    @contextlib.contextmanager
    def failing(path, mode="wb", tag=""):
        path = Path(path)
        calls[path.name] = calls.get(path.name, 0) + 1
        with real(path, mode, tag) as fh:
            hit = (where == "shard" and path.name == "shard-000001.tar") or (where == "manifest" and path.name == "manifest.json" and calls[path.name] == 2)
            yield _FullDisk(fh, [len(reference["shard-000001.tar"]) // 2 if where == "shard" else 10]) if hit else fh

    monkeypatch.setattr(shards, "atomic_write", failing)
    out = tmp_path / "out"
    cfg = _config(tmp_path)
    rc, err = run(capfd, "generate", cfg, "--out", out)
    lines = [line for line in err.splitlines() if not line.startswith("[synth]")]  # progress lines
    failed = out / ("shard-000001.tar" if where == "shard" else "manifest.json")
    assert_refused(rc, "\n".join(lines), failed, "cannot write (no space left on device); the finished shards are kept, continue with --resume")
    man = json.loads((out / "manifest.json").read_text())
    assert list(man["shards"]) == ["shard-000000.tar"] and not man["complete"]
    assert (out / "shard-000000.tar").read_bytes() == reference["shard-000000.tar"]
    assert not list(out.glob(".*.tmp")) and not list(out.glob(".lock*"))
    monkeypatch.setattr(shards, "atomic_write", real)  # space freed
    rc, err = run(capfd, "generate", cfg, "--out", out, "--resume")
    assert rc == 0, err
    assert _shards(out) == reference
    assert json.loads((out / "manifest.json").read_text())["complete"]


@pytest.mark.parametrize("out_exists", [False, True])
def test_bad_input_found_under_the_lock_leaves_the_folder_as_it_was(tmp_path, fake_run, capfd, monkeypatch, out_exists):
    """An error found after the folder is locked (here: a subject that cannot be made) removes what
    the run made: the subjects folder, the lock, and the output folder when the run created it."""
    out = tmp_path / "parent" / "out"
    if out_exists:
        out.mkdir(parents=True)
        (out / "notes.txt").write_text("mine")
    bad = out / "subjects" / "anny_0000.npz"

    def prepare(cfg, out_, model):
        (out_ / "subjects").mkdir()
        raise ValueError(f"{bad}: subject made with other settings (seed differs)")

    monkeypatch.setattr(fake_run, "prepare_subjects", prepare)
    cfg = _config(tmp_path)
    before = snapshot(tmp_path)
    rc, err = run(capfd, "generate", cfg, "--out", out)
    assert_refused(rc, err, bad, "subject made with other settings", before, tmp_path)


# ------------------------------------------------------------------------------------------------
# The validator's keypoint tolerance: derived from the JSON's 6 decimals


def _stored(kp: np.ndarray, cam: Camera) -> tuple[dict, Camera]:
    """A person's keypoint labels and the camera as the generator writes them (6 decimals)."""
    kc = kp.astype(np.float64) @ cam.R.T + cam.t
    person = {"keypoints_3d": fmt.json_round(kp), "keypoints_3d_cam": fmt.json_round(kc), "keypoints_2d": fmt.json_round(cam.project(kp))}
    rounded = Camera(K=np.array(fmt.json_round(cam.K)), R=np.array(fmt.json_round(cam.R)), t=np.array(fmt.json_round(cam.t)), width=cam.width, height=cam.height)
    return person, rounded


@pytest.fixture(scope="module")
def bodies(model):
    import torch

    g = torch.Generator().manual_seed(0)
    with torch.no_grad():
        out = model(pose=0.6 * torch.randn(4, 47, generator=g), global_orient=0.3 * torch.randn(4, 3, generator=g))
    return out.keypoints.numpy(), out.vertices.numpy()


def test_correct_rare_long_lens_far_samples_pass(bodies):
    from synth.camera import CameraConfig, sample_camera

    kps, verts = bodies
    cfg = CameraConfig(width=192, height=192, focal_mm=(200.0, 800.0), rare_rate=1.0, fill=(0.1, 0.9), truncation_rate=0.5)
    far = 0
    for i in range(60):
        shift = np.float32([2.5 * (i % 3), 0.0, -1.5 * (i % 5)])  # people away from the origin too
        cam, info = sample_camera(verts[i % 4] + shift, cfg, np.random.default_rng(i))
        far += info["distance"] > 20
        person, stored = _stored(kps[i % 4] + shift, cam)
        assert check_keypoints(stored, person) == [], (i, info)
    assert far > 10


def test_worst_case_rounding_passes_where_the_old_1e3_px_tolerance_failed(model):
    """A correct label whose stored values all rounded the same way (each within 5e-7 of the truth,
    as 6 decimals allow) with a long lens on a keypoint near the camera: it was 'wrong by > 1e-3 px'."""
    f = 3000.0
    grid = 1e-6
    K = np.array([[f, 0, 96.0], [0, f, 96.0], [0, 0, 1.0]])
    R, t = np.eye(3), np.array([0.0, 0.0, 1.2])
    X = np.array([[0.021, 0.013, 0.2]])  # stored (on the 6-decimal grid)
    e = 0.49 * grid
    X_true = X + np.array([e, e, -e])  # every rounding pushed the projection the same way
    t_true = t + np.array([e, e, -e])
    K_true = K.copy()
    K_true[0, 0] += e
    K_true[0, 2] += e
    uv = (X_true @ R.T + t_true) @ K_true.T
    uv = uv[:, :2] / uv[:, 2:]
    person = {"keypoints_3d": X.tolist(), "keypoints_3d_cam": fmt.json_round(X_true @ R.T + t_true), "keypoints_2d": fmt.json_round(uv)}
    cam = Camera(K=K, R=R, t=t, width=192, height=192)
    err = np.abs(cam.project(X) - np.array(person["keypoints_2d"])).max()
    assert err > 1e-3  # the old KEYPOINT_PX
    assert check_keypoints(cam, person) == []
    assert fmt.projection_tolerance(X, K, R, t).max() < 0.05


@pytest.mark.parametrize("k, axis", [(0, 0), (5, 1), (17, 0), (40, 1)])
def test_a_keypoint_moved_by_005_px_fails(bodies, k, axis):
    from synth.camera import CameraConfig, sample_camera

    kps, verts = bodies
    cfg = CameraConfig(width=192, height=192, focal_mm=(300.0, 800.0), rare_rate=1.0, truncation_rate=0.0)
    cam, _ = sample_camera(verts[1], cfg, np.random.default_rng(k))
    person, stored = _stored(kps[1], cam)
    assert check_keypoints(stored, person) == []
    person["keypoints_2d"][k][axis] += 0.05
    msgs = check_keypoints(stored, person)
    assert len(msgs) == 1 and msgs[0].startswith("keypoints_2d are not the projection of keypoints_3d (5.0"), msgs
    moved = dict(person, keypoints_2d=fmt.json_round(cam.project(kps[1])))
    moved["keypoints_3d_cam"] = [list(r) for r in person["keypoints_3d_cam"]]
    moved["keypoints_3d_cam"][k][2] += 1e-4
    assert any("keypoints_3d_cam is not R keypoints_3d + t" in m for m in check_keypoints(stored, moved))



# ------------------------------------------------------------------------------------------------
# Partitioned runs (--part I/N) and synth merge


@pytest.mark.parametrize("arg, problem", [
    ("x", "--part must be I/N (e.g. 2/8), got 'x'"),
    ("1/2/3", "--part must be I/N"),
    ("0/3", "--part 0/3: I must be in [1, N]"),
    ("4/3", "--part 4/3: I must be in [1, N]"),
    ("3/8", "part 3/8 has no shards: the dataset has 2"),
])
def test_bad_part_argument(tmp_path, capfd, fake_run, arg, problem):
    cfg = _config(tmp_path)
    before = snapshot(tmp_path)
    rc, err = run(capfd, "generate", cfg, "--out", tmp_path / "out", "--part", arg)
    assert rc == 2 and len(err.splitlines()) == 1 and problem in err and "Traceback" not in err, err
    assert snapshot(tmp_path) == before


def test_address_without_the_ray_engine(tmp_path, capfd, fake_run):
    cfg = _config(tmp_path)
    before = snapshot(tmp_path)
    rc, err = run(capfd, "generate", cfg, "--out", tmp_path / "out", "--address", "127.0.0.1:6379")
    assert rc == 2 and err.strip() == "synth: error: --address needs --engine ray", err
    assert snapshot(tmp_path) == before


def _parts(tmp_path: Path, capfd, *which: str) -> Path:
    out = tmp_path / "out"
    for part in which:
        rc, err = run(capfd, "generate", _config(tmp_path), "--out", out, "--part", part)
        assert rc == 0, err
    return out


MERGE_CASES = ["no_folder", "no_parts", "garbage_part_manifest", "renamed_part_manifest", "damaged_shard",
               "missing_shard", "unfinished_part", "parts_of_two_runs", "mixed_partitions"]


@pytest.mark.parametrize("case", MERGE_CASES)
def test_bad_merge_is_one_line_and_changes_nothing(tmp_path, capfd, fake_run, case):
    out = tmp_path / "out"
    if case == "no_folder":
        bad, problem = out, "no such dataset folder"
    elif case == "no_parts":
        out.mkdir()
        bad, problem = out, "no part manifests (manifest-part-I-of-N.json) to merge"
    else:
        _parts(tmp_path, capfd, "1/2", "2/2")
        p1, p2 = out / "manifest-part-1-of-2.json", out / "manifest-part-2-of-2.json"
        if case == "garbage_part_manifest":
            p2.write_bytes(b"\xff\x00garbage")
            bad, problem = p2, "unreadable manifest"
        elif case == "renamed_part_manifest":
            p2.rename(out / "manifest-part-3-of-4.json")
            bad, problem = out / "manifest-part-3-of-4.json", "holds part 2/2 (renamed?)"
        elif case == "damaged_shard":
            shard = out / "shard-000001.tar"
            data = bytearray(shard.read_bytes())
            data[700] ^= 0xFF
            shard.write_bytes(bytes(data))
            bad, problem = shard, "SHA-256 differs from manifest-part-2-of-2.json"
        elif case == "missing_shard":
            (out / "shard-000000.tar").unlink()
            bad, problem = out / "shard-000000.tar", "missing (listed in manifest-part-1-of-2.json)"
        elif case == "unfinished_part":
            man = json.loads(p2.read_text())
            man["shards"], man["complete"] = {}, False
            p2.write_text(json.dumps(man))
            bad, problem = p2, "part 2/2 is unfinished (0 of 1 shards); continue it with --part 2/2 --resume"
        elif case == "parts_of_two_runs":
            man = json.loads(p2.read_text())
            man["seed"] = 99
            p2.write_text(json.dumps(man))
            bad, problem = p2, "seed differs from this run; not a part of the run of manifest-part-1-of-2.json"
        else:  # mixed_partitions: part 2/3 (shard 1) run after the parts of 2
            rc, err = run(capfd, "generate", _config(tmp_path), "--out", out, "--part", "2/3", "--resume")
            assert rc == 0, err
            bad, problem = out / "manifest-part-2-of-3.json", "claims shard-000001.tar, which manifest-part-2-of-2.json claims too"
    before = snapshot(tmp_path)
    rc, err = run(capfd, "merge", out)
    assert_refused(rc, err, bad, problem, before, tmp_path)


def test_merge_while_a_part_runs_is_refused(tmp_path, capfd, fake_run):
    out = _parts(tmp_path, capfd, "1/2")
    with out_lock.acquire(out, 2, 2):
        before = snapshot(tmp_path)
        rc, err = run(capfd, "merge", out)
        assert_refused(rc, err, out, "in use by another synth generate", before, tmp_path)
    rc, err = run(capfd, "generate", _config(tmp_path), "--out", out, "--part", "2/2")
    assert rc == 0, err
    rc, err = run(capfd, "merge", out)
    assert rc == 0, err
    assert json.loads((out / "manifest.json").read_text())["complete"]
    assert not list(out.glob("manifest-part-*")) and not list(out.glob(".lock*"))


def test_ray_address_where_nothing_answers(tmp_path, capfd, fake_run):
    """Checked before anything is made (Ray itself would keep retrying for minutes)."""
    pytest.importorskip("ray", reason="Ray is not installed (pip install 'blsm-synth[ray]')")
    cfg = _config(tmp_path)
    before = snapshot(tmp_path)
    rc, err = run(capfd, "generate", cfg, "--out", tmp_path / "out", "--engine", "ray", "--address", "127.0.0.1:1")
    assert rc == 2 and len(err.splitlines()) == 1, err
    assert err.startswith("synth: error: --address 127.0.0.1:1: no Ray cluster answers there"), err
    assert snapshot(tmp_path) == before
