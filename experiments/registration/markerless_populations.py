"""The stand-in scan populations of the markerless registration measurements (docs/markerless.md).

    python experiments/registration/markerless_populations.py [--out out/register4d]

Writes, each once (an existing folder is kept):

- ``val``: the validation population, on which fitting settings are chosen (seed 505, 8 subjects,
  4 of them with one posed scan; 12 scans);
- ``heldout``: the held-out population every reported number is on (seed 101, 12 subjects, 6 with
  one posed scan; 18 scans);
- ``heldout2``: a second held-out population, made after the 2026-12-01 defaults were chosen, to
  check the held-out number on other subjects (seed 707, 12 subjects, 6 with one posed scan);
- ``extra_stool``: one subject with a stool and 6 floor markers (seed 202);
- ``extra_nofeet``: one subject without feet (seed 303);
- ``extra/stool.npz``, ``extra/nofeet.npz``: the scans of the last two under names of their own (the
  measurements name results by file name, and every population starts at ``s00000_00``).

All textured, default scanner artefacts, split ``test``. Every draw derives from (seed, subject), so
the folders are the same on any machine (``blsm.learn.scans.population.make_population``).
"""

from __future__ import annotations

import argparse
import shutil
from pathlib import Path

POPULATIONS = {  # name: (subjects, posed subjects, seed, artefacts)
    "val": (8, 4, 505, {}),
    "heldout": (12, 6, 101, {}),
    "heldout2": (12, 6, 707, {}),
    "extra_stool": (1, 0, 202, {"stool": True, "floor_markers": 6}),
    "extra_nofeet": (1, 0, 303, {"missing_feet": True}),
}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--out", type=Path, default=Path("out/register4d"))
    ap.add_argument("--only", nargs="*", choices=sorted(POPULATIONS), default=None)
    args = ap.parse_args()
    from blsm.learn.scans.population import Artefacts, make_population

    for name, (n, posed, seed, art) in POPULATIONS.items():
        if args.only and name not in args.only:
            continue
        folder = args.out / name
        if (folder / "index.json").exists():
            print(f"{folder}: kept", flush=True)
            continue
        make_population(folder, n, posed_subjects=posed, poses_per_subject=1 if posed else 0, seed=seed,
                        test_fraction=1.0, artefacts=Artefacts(**art))
        print(f"{folder}: {len(list((folder / 'scans').glob('*.npz')))} scans", flush=True)
    extra = args.out / "extra"
    extra.mkdir(parents=True, exist_ok=True)
    for name in ("stool", "nofeet"):
        src, dst = args.out / f"extra_{name}" / "scans" / "s00000_00.npz", extra / f"{name}.npz"
        if src.exists() and not dst.exists():
            shutil.copyfile(src, dst)


if __name__ == "__main__":
    main()
