"""Byte-identity of ``synth generate`` across a refactor (issue 33): the same config and seed must
give the same shards, manifests and index files before and after.

    python scripts/identity_check.py --out DIR [--repo REPO] [--ray] [--only NAME ...]
    python scripts/identity_check.py --rehash DIR
    python scripts/identity_check.py --compare A/identity.json B/identity.json

The first form generates a small dataset for each entry of :data:`RUNS` with ``python -m synth.cli
generate`` run in ``REPO`` (default: this checkout; ``REPO`` is put first on ``PYTHONPATH`` so that
its code is the code imported) and writes ``DIR/identity.json``: run name -> {file: sha256}. The
second hashes the datasets already in ``DIR`` again (into ``DIR/identity.json``); the third prints
every difference between two such files and exits 1 if there is any.

What is hashed: every file under each dataset folder, hidden ones included, by its bytes: shards,
manifests, ``subjects/*.npz`` and ``subjects/index.json``. Nothing is left out, since nothing
varies from run to run: a finished run leaves no lock naming its process (a part's
``.lock-subjects``, kept until ``synth merge``, is empty), the manifests hold no time, host or
working directory, and ``np.savez`` writes the subjects' zip entries with a fixed date (the
subjects of separate runs are the same bytes).

Every path the configs name (HDRIs, backplates, motion libraries) is given as an absolute path,
so that the manifests (which store the config) do not depend on the working directory.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import os
import shutil
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
HDRI = str(ROOT.parent / "shared" / "assets" / "hdri")
MOTIONS = str(ROOT / "out" / "motions")
MOTIONS_TEST = str(ROOT / "out" / "motions_test")
PLATES = str(Path("~/.cache/blsm-synth/backplates").expanduser())

SMALL = ["camera.width=64", "camera.height=64", "subjects.count=2", "subjects.texture_size=256",
         "render.spp=4", "output.shard_size=4", "background.env_width=256"]
SEQ = ["sequence.frames=8", "sequence.per_shard=1"]

# name -> (config, --set overrides, extra command-line arguments)
RUNS: dict[str, tuple[str, list[str], list[str]]] = {
    "default": ("configs/synth/default.yaml", SMALL, ["--num", "6", "--workers", "2"]),
    "default-stop-after": ("configs/synth/default.yaml", SMALL, ["--num", "6", "--stop-after", "1"]),
    "default-part-1-of-2": ("-", SMALL, ["--num", "6", "--part", "1/2"]),
    "hdri": ("configs/synth/hdri.yaml", [*SMALL, f"background.folder={HDRI}"], ["--num", "6"]),
    "mocap": ("configs/synth/mocap.yaml", [*SMALL, f"background.folder={HDRI}", f"poses.library={MOTIONS}"],
              ["--num", "6"]),
    "transfer-plates": ("configs/synth/transfer/plates.yaml", [*SMALL, f"background.folder={PLATES}"],
                        ["--num", "6", "--workers", "2"]),
    "video_test": ("configs/synth/video_test.yaml",
                   [*SMALL, *SEQ, f"background.folder={HDRI}", f"poses.library={MOTIONS_TEST}"],
                   ["--num", "2", "--workers", "2"]),
    "video_test-blur": ("configs/synth/video_test.yaml",
                        [*SMALL, *SEQ, f"background.folder={HDRI}", f"poses.library={MOTIONS_TEST}",
                         "sequence.motion_blur.enabled=true", "sequence.motion_blur.subframes=3"],
                        ["--num", "1"]),
    "blsm_subdivided": ("configs/synth/blsm_subdivided.yaml", [*SMALL, f"background.folder={HDRI}"],
                        ["--num", "6"]),
}
RAY_RUNS: dict[str, tuple[str, list[str], list[str]]] = {
    "default-ray": ("configs/synth/default.yaml", SMALL, ["--num", "6", "--engine", "ray"]),
}


def dataset_hashes(root: Path) -> dict[str, str]:
    """{relative path: sha256} of every file of a dataset folder."""
    return {str(p.relative_to(root)): hashlib.sha256(p.read_bytes()).hexdigest()
            for p in sorted(root.rglob("*")) if p.is_file()}


def run(name: str, spec: tuple[str, list[str], list[str]], repo: Path, work: Path) -> dict[str, str]:
    config, sets, extra = spec
    out = work / name
    if out.exists():
        shutil.rmtree(out)
    cmd = [sys.executable, "-m", "synth.cli", "generate", config, "--out", str(out), *extra]
    for s in sets:
        cmd += ["--set", s]
    env = {**os.environ, "PYTHONPATH": str(repo) + os.pathsep + os.environ.get("PYTHONPATH", "")}
    t0 = time.time()
    print(f"[identity] {name}: {' '.join(cmd)}", flush=True)
    res = subprocess.run(cmd, cwd=repo, env=env, capture_output=True, text=True)
    if res.returncode != 0:
        raise SystemExit(f"[identity] {name} failed ({res.returncode}):\n{res.stdout}\n{res.stderr[-4000:]}")
    print(f"[identity] {name}: {res.stdout.strip()} ({time.time() - t0:.0f} s)", flush=True)
    return dataset_hashes(out)


def compare(a: Path, b: Path) -> int:
    da, db = json.loads(a.read_text()), json.loads(b.read_text())
    diffs = []
    for name in sorted(set(da) | set(db)):
        if name not in da or name not in db:
            diffs.append(f"{name}: only in {a if name in da else b}")
            continue
        fa, fb = da[name], db[name]
        for f in sorted(set(fa) | set(fb)):
            if fa.get(f) != fb.get(f):
                diffs.append(f"{name}/{f}: {fa.get(f, 'absent')} != {fb.get(f, 'absent')}")
    n = sum(len(v) for v in da.values())
    for d in diffs:
        print(d)
    print(f"{len(da)} runs, {n} files in {a}; {len(diffs)} differences")
    return 1 if diffs else 0


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--out", type=Path, help="folder for the datasets and identity.json")
    p.add_argument("--repo", type=Path, default=ROOT, help="the checkout whose code runs (default: this one)")
    p.add_argument("--ray", action="store_true", help="also the Ray engine run (needs ray)")
    p.add_argument("--only", nargs="*", help="only these runs")
    p.add_argument("--rehash", type=Path, metavar="DIR", help="hash the datasets already in DIR again")
    p.add_argument("--compare", nargs=2, type=Path, metavar=("A", "B"))
    args = p.parse_args()
    if args.compare:
        return compare(*args.compare)
    if args.rehash:
        folders = [d for d in sorted(args.rehash.iterdir()) if (d / "subjects").is_dir()]
        result = {d.name: dataset_hashes(d) for d in folders}
        (args.rehash / "identity.json").write_text(json.dumps(result, indent=1, sort_keys=True) + "\n")
        print(f"[identity] {args.rehash / 'identity.json'}: {len(result)} runs")
        return 0
    if args.out is None:
        p.error("--out or --compare is needed")
    runs = {**RUNS, **(RAY_RUNS if args.ray else {})}
    if args.only:
        runs = {k: v for k, v in runs.items() if k in args.only}
    args.out.mkdir(parents=True, exist_ok=True)
    result_path = args.out / "identity.json"
    result = json.loads(result_path.read_text()) if result_path.exists() else {}
    for name, spec in runs.items():
        result[name] = run(name, spec, args.repo.resolve(), args.out)
        result_path.write_text(json.dumps(result, indent=1, sort_keys=True) + "\n")
    print(f"[identity] {result_path}: {len(result)} runs")
    return 0


if __name__ == "__main__":
    sys.exit(main())
