"""Plausible people and poses (issue 18): the default population's ages and the prior's re-draws.

    python benchmarks/bench_realism.py --out docs/realism.md [--poses 10000] [--people 10000]

Writes two sections of ``--out`` (between ``<!-- bench:... -->`` markers) and
``docs/figures/realism_ages.png`` (``figures/`` beside ``--out``):

- **poses**: ``--poses`` prior draws through the generator's own ``PoseSource`` (seed 0), with and
  without ``poses.plausible``: feet pointing backwards relative to the pelvis (the leg
  straightened, :mod:`blsm.mocap.plausible`), toes behind the heel as posed (information), limbs
  through the torso, and the re-draw (rejection) rate;
- **ages**: the ages of ``--people`` people of the default population against Anny's own (0-90);
- **noise** (``--noise CONFIG``): the same ``--scenes`` scenes of a generator config rendered as the
  generator did before this work (independent sampler, 16 spp, no denoiser, no shadow catcher, no
  hair: ``before``), undenoised at 128 spp (the acceptance's bar), with each ``--render`` setting
  (a Mitsuba sampler, spp, with or without the denoiser), the defaults' render settings without
  and with the shadow catcher and hair, and with every new default
  (``after``), against a 1024-spp undenoised reference of the same scenes (with shadows and hair for
  ``after``); PSNR of the written 8-bit sRGB images and time per image (the
  whole sample, labels included), alternating rounds, medians. Subjects are made once into
  ``--work``.
"""

from __future__ import annotations

import argparse
import re
import time
from pathlib import Path

import numpy as np
import torch


def _replace_section(path: Path, name: str, body: str) -> None:
    start, end = f"<!-- bench:{name} -->", f"<!-- /bench:{name} -->"
    text = path.read_text() if path.exists() else ""
    block = f"{start}\n{body.rstrip()}\n{end}"
    if start in text and end in text:
        text = re.sub(re.escape(start) + r".*?" + re.escape(end), lambda _: block, text, flags=re.S)
    else:
        text = text.rstrip() + ("\n\n" if text else "") + block + "\n"
    path.write_text(text)


def poses_section(n: int) -> str:
    import blsm
    from blsm.mocap.plausible import PoseChecker
    from synth.config import GeneratorConfig, PosesConfig
    from synth.poses import PoseSource

    checker = PoseChecker(blsm.load())
    rows = []
    for plausible in (False, True):
        src = PoseSource(GeneratorConfig(poses=PosesConfig(plausible=plausible)))
        rng = np.random.default_rng(0)
        t0 = time.perf_counter()
        xs, redraws = [], 0
        for _ in range(n):
            x, _, motion = src.sample(rng)
            xs.append(x)
            redraws += motion.get("redraws", 0)
        dt = time.perf_counter() - t0
        r = checker.check(torch.from_numpy(np.stack(xs)))
        rows.append((plausible, r, redraws, dt))
    lines = [
        f"{n} prior poses drawn by `synth.poses.PoseSource` (seed 0, the packaged CMU prior), checked on the",
        "mean body by `blsm.mocap.plausible`:",
        "",
        "| `poses.plausible` | feet backwards, leg straightened (L / R) | toes behind heel as posed (L / R) | limb through torso | re-draws | rejection rate | ms per pose |",
        "| --- | ---: | ---: | ---: | ---: | ---: | ---: |",
    ]
    for plausible, r, redraws, dt in rows:
        fb, th = r.foot_backwards.sum(0), r.toes_behind_heel.sum(0)
        rate = f"{100.0 * redraws / (n + redraws):.2f} %" if plausible else "-"
        lines.append(f"| {str(plausible).lower()} | {fb[0]} / {fb[1]} | {th[0]} / {th[1]} | {int(r.limb_in_torso.sum())} | "
                     f"{redraws if plausible else '-'} | {rate} | {1000.0 * dt / n:.2f} |")
    lines += ["", "The rejection rate is re-draws over all draws made. Command: `python benchmarks/bench_realism.py`."]
    return "\n".join(lines)


def ages_section(n: int, png: Path, link: str) -> str:
    """The ages section; its histogram written to ``png``, linked from the markdown as ``link``."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from synth.subjects import Population, sample_phenotype

    bins = [0, 2, 5, 10, 18, 30, 40, 50, 60, 70, 80, 90]
    pops = {"default (adults 18-80, 10 % children 5-17)": Population(), "Anny's own (0-90, `age: [0, 90], children: 0`)": Population.ANNY}
    ages = {k: np.array([sample_phenotype(np.random.default_rng(i), p)["age_years"] for i in range(n)]) for k, p in pops.items()}
    fig, ax = plt.subplots(figsize=(7, 3.2))
    for k, a in ages.items():
        ax.hist(a, bins=np.arange(0, 91, 2.5), alpha=0.6, label=k)
    ax.set_xlabel("age (years, Anny's morphological age)")
    ax.set_ylabel(f"people of {n}")
    ax.legend(fontsize=8)
    fig.tight_layout()
    png.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(png, dpi=110)
    plt.close(fig)
    head = "| ages | " + " | ".join(f"{lo}-{hi}" for lo, hi in zip(bins[:-1], bins[1:])) + " |"
    lines = [f"Ages of {n} people per population (`sample_phenotype`, seeds 0..{n - 1}); ![ages]({link})", "", head,
             "| --- |" + " ---: |" * (len(bins) - 1)]
    for k, a in ages.items():
        counts = np.histogram(a, bins=bins)[0]
        lines.append(f"| {k} | " + " | ".join(str(c) for c in counts) + " |")
    return "\n".join(lines)


def time_scenes(maker, seed: int, scenes: int) -> tuple[list[dict], float]:
    """Samples 1..``scenes`` of ``maker`` (a ``synth.sample.SampleMaker``) and the seconds per
    sample spent making them, after a warm-up sample (kernels compile once) and rigging every subject
    (per-subject work, the render mesh and hair, is made once). benchmarks/time_images.py times an
    older checkout with it too."""
    from synth.dataset.shards import sample_rng

    maker.make(0, sample_rng(seed, 0))
    for si in range(len(maker.subjects)):
        maker.rig(si)
    t0 = time.perf_counter()
    samples = [maker.make(i, sample_rng(seed, i)) for i in range(1, scenes + 1)]
    return samples, (time.perf_counter() - t0) / scenes


def noise_section(config: str, work: Path, scenes: int, specs: list[str], ref_spp: int, rounds: int) -> str:
    import dataclasses

    import blsm
    from blsm.mitsuba_util import resolve_variant
    from synth.config import load_config
    from synth.dataset import format as fmt
    from synth.denoise import psnr
    from synth.generate import prepare_subjects
    from synth.sample import SampleMaker

    base = load_config(config)
    work.mkdir(parents=True, exist_ok=True)
    prepare_subjects(base, work, blsm.load())
    variant = resolve_variant(base.render.variant or None)

    def variant_cfg(spp: int, denoise: bool, shadows: bool, hair: bool = False, sampler: str = "independent"):
        return dataclasses.replace(base, render=dataclasses.replace(base.render, spp=spp, denoise=denoise, sampler=sampler),
                                   ground=dataclasses.replace(base.ground, shadows=shadows),
                                   hair=dataclasses.replace(base.hair, enabled=hair))

    conds = {"before: independent 16 spp, no denoiser, no shadows, no hair": variant_cfg(16, False, False),
             "independent 128 spp, no denoiser, no shadows, no hair (the bar)": variant_cfg(128, False, False)}
    for spec in specs:  # sampler:spp[:dn]
        sampler, spp, *dn = spec.split(":")
        conds[f"{sampler} {spp} spp, {'denoiser' if dn else 'no denoiser'}, no shadows, no hair"] = variant_cfg(
            int(spp), bool(dn), False, False, sampler)
    r0 = base.render
    name0 = f"{r0.sampler} {r0.spp} spp, {'denoiser' if r0.denoise else 'no denoiser'}"
    conds[f"defaults' render ({name0}), no shadows, no hair"] = variant_cfg(r0.spp, r0.denoise, False, False, r0.sampler)
    conds[f"{name0}, shadows, no hair"] = variant_cfg(r0.spp, r0.denoise, True, False, r0.sampler)
    conds[f"{name0}, no shadows, hair"] = variant_cfg(r0.spp, r0.denoise, False, True, r0.sampler)
    conds[f"after: every default ({name0}, shadows, hair)"] = base
    # The old render settings and the bar on the defaults' content (shadows and hair): the render
    # settings' cost and gain at equal content.
    old_on_content = "independent 16 spp, no denoiser, shadows, hair"
    conds[old_on_content] = variant_cfg(16, False, True, True)
    conds["independent 128 spp, no denoiser, shadows, hair (the bar with this content)"] = variant_cfg(128, False, True, True)
    # The references: the same scenes at ref_spp undenoised, without and with the shadows and hair.
    scene_of = {name: (cfg.ground.shadows, cfg.hair.enabled) for name, cfg in conds.items()}
    ref_cfgs = {k: variant_cfg(ref_spp, False, *k) for k in set(scene_of.values())}

    def render_all(cfg) -> tuple[list[np.ndarray], float]:
        samples, seconds = time_scenes(SampleMaker(cfg, work, variant, threads=0), cfg.seed, scenes)
        return [fmt.decode_png(s["rgb.png"], "rgb") for s in samples], seconds

    refs = {k: render_all(c)[0] for k, c in ref_cfgs.items()}
    times: dict[str, list[float]] = {k: [] for k in conds}
    quality: dict[str, float] = {}
    for _ in range(rounds):
        for name, cfg in conds.items():
            imgs, t = render_all(cfg)
            times[name].append(t)
            ref = refs[scene_of[name]]
            quality[name] = float(np.mean([psnr(a / 255.0, b / 255.0) for a, b in zip(imgs, ref)]))
            print(f"[bench_realism] {name}: {quality[name]:.3f} dB, {t:.3f} s per image", flush=True)
    before = float(np.median(times[next(iter(conds))]))
    # Each row's time against the old render settings (independent 16 spp) on the same content.
    same_before = {(False, False): before, (True, True): float(np.median(times[old_on_content]))}
    lines = [
        f"`{config}`: {scenes} scenes ({base.camera.width} x {base.camera.height} px), reference {ref_spp} spp undenoised "
        f"of the same scenes (with the shadow catcher and hair where the row has them), {rounds} rounds, this machine's cores; "
        f"time: the median round (every round's time is in the log). The PSNR needs the same scenes in every round; "
        f"since issue 34 the generator compiles no kernel per scene (tests/synth/test_generate.py), so a scene seen "
        f"before costs what a new one does. benchmarks/bench_generate.py times fresh samples.",
        "",
        "| render | PSNR (dB) | s per image | time vs before | time vs independent 16 spp, same content |",
        "| --- | ---: | ---: | ---: | ---: |",
    ]
    for name in conds:
        t = float(np.median(times[name]))
        same = same_before.get(scene_of[name])
        lines.append(f"| {name} | {quality[name]:.2f} | {t:.3f} | {t / before:.2f} | {'-' if same is None else f'{t / same:.2f}'} |")
    lines += ["", f"Command: `python benchmarks/bench_realism.py --noise {config} --scenes {scenes} "
              f"--render {' '.join(specs)} --ref-spp {ref_spp} --rounds {rounds}`."]
    return "\n".join(lines)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--out", default="docs/realism.md")
    ap.add_argument("--poses", type=int, default=10000)
    ap.add_argument("--people", type=int, default=10000)
    ap.add_argument("--noise", metavar="CONFIG", help="also measure the denoiser (a generator config)")
    ap.add_argument("--work", default="out/bench_realism", help="subjects for --noise")
    ap.add_argument("--scenes", type=int, default=12)
    ap.add_argument("--render", nargs="+", default=["independent:16:dn", "multijitter:16", "multijitter:25",
                                                    "multijitter:36", "multijitter:16:dn", "multijitter:25:dn"],
                    help="render settings to compare, SAMPLER:SPP[:dn] (dn: with the denoiser)")
    ap.add_argument("--ref-spp", type=int, default=1024)
    ap.add_argument("--rounds", type=int, default=2)
    ap.add_argument("--skip", nargs="*", default=[], choices=["poses", "ages"], help="sections not to run")
    args = ap.parse_args()
    torch.set_num_threads(1)
    out = Path(args.out)
    if args.noise:
        _replace_section(out, "realism-noise", noise_section(args.noise, Path(args.work), args.scenes, args.render,
                                                             args.ref_spp, args.rounds))
        print(f"noise: {out}")
    if "poses" not in args.skip:
        _replace_section(out, "realism-poses", poses_section(args.poses))
        print(f"poses: {out}")
    if "ages" not in args.skip:
        png = out.parent / "figures" / "realism_ages.png"
        _replace_section(out, "realism-ages", ages_section(args.people, png, "figures/realism_ages.png"))
        print(f"ages: {out}, {png}")


if __name__ == "__main__":
    main()
