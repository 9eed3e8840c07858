"""The generator: subjects, poses, cameras and backgrounds to labelled images in shards.

``generate(config, out, ...)`` makes ``out/subjects/`` (the people, once per dataset, from the seed)
and then the shards. A sample's randomness is ``sample_rng(seed, index)`` only, so any worker can
make any sample, and a resumed run makes the same dataset as an uninterrupted one. Each worker
process loads the model, subjects and backgrounds once and keeps one Mitsuba scene per mesh
topology, updated in place per image; a worker is replaced after ``render.recycle_after`` images.

Before any work, every input file is opened and checked (:func:`check_inputs`) and the output
folder is locked for this writer (:mod:`synth.lock`); bad input leaves no new file or folder, and a
failed write (a full disk) keeps the finished shards for ``--resume``.
"""

from __future__ import annotations

import contextlib
import itertools
import json
import math
import multiprocessing as mp
import os
import shutil
import sys
import time
from collections.abc import Callable, Iterator
from dataclasses import asdict
from pathlib import Path
from typing import Any

import numpy as np
import torch

from blsm import mitsuba_util
from blsm.color import linear_to_srgb, srgb_to_linear
from blsm.io import atomic_write, sha256_file
from synth import backgrounds as bg
from synth import format as fmt
from synth import labels as lab
from synth import lock as out_lock
from synth.camera import outline_index, sample_camera
from synth.config import GeneratorConfig
from synth.render import PeopleRenderer, RenderMesh, people_window
from synth.sequence import move_person, sequence_rng
from synth.shards import ShardWriter, SkipSample, WriteError, sample_rng
from synth.subjects import Subject, anny_subject, load_subject, model_fingerprint, pose_subject, save_subject

SUBJECTS = "subjects"
SUBJECTS_LOCK = ".lock-subjects"
ENGINES = ("local", "ray")


def _log(msg: str) -> None:
    print(f"[synth] {msg}", file=sys.stderr, flush=True)


def versions() -> dict[str, str]:
    import drjit
    import mitsuba

    import blsm

    out = {"python": sys.version.split()[0], "numpy": np.__version__, "torch": torch.__version__}
    out["mitsuba"], out["drjit"] = mitsuba.__version__, drjit.__version__
    out["blsm"] = getattr(blsm, "__version__", "0.1.0")
    return out


def choose_variant(cfg: GeneratorConfig) -> str:
    """The Mitsuba variant, once per run: the configured one, else cuda where a GPU is, else llvm."""
    if cfg.render.variant:
        return mitsuba_util.choose_variant((cfg.render.variant,))
    cands = ("cuda_ad_rgb", "llvm_ad_rgb", "scalar_rgb") if shutil.which("nvidia-smi") else ("llvm_ad_rgb", "scalar_rgb")
    return mitsuba_util.choose_variant(cands)


# ------------------------------------------------------------------------------------------------
# Subjects


def subject_rng(seed: int, i: int) -> np.random.Generator:
    # A three-word seed sequence: never equal to a sample's (seed, index).
    return np.random.Generator(np.random.PCG64(np.random.SeedSequence([int(seed), 1, int(i)])))


def prepare_subjects(cfg: GeneratorConfig, out: Path, model: Any) -> list[Path]:
    """Make (or reuse) ``out/subjects/*.npz`` and ``subjects/index.json``; return the files."""
    folder = out / SUBJECTS
    folder.mkdir(parents=True, exist_ok=True)
    paths: list[Path] = []
    skipped: list[dict[str, str]] = []
    if cfg.subjects.source == "anny":
        # A subject depends on the model (its registration), the seed and the texture size: one
        # made with other ones must not be reused, or a resumed run would not be the same dataset.
        stamp = {"model": model_fingerprint(model), "seed": cfg.seed, "texture_size": cfg.subjects.texture_size,
                 "population": json.loads(json.dumps(asdict(cfg.subjects.population())))}  # as stored (lists)
        for i in range(cfg.subjects.count):
            path = folder / f"anny_{i:04d}.npz"
            if path.exists():  # written atomically, so complete: a damaged one is an error
                had = load_subject(path).meta.get("made_with")
                if had != stamp:
                    what = "an earlier version" if had is None else ", ".join(
                        k for k in stamp if had.get(k) != stamp[k]) + " differs"
                    raise ValueError(f"{path}: subject made with other settings ({what}); "
                                     "remove the dataset's subjects folder or use another --out")
                paths.append(path)
                continue
            t0 = time.time()
            s = anny_subject(model, path.stem, subject_rng(cfg.seed, i), cfg.subjects.texture_size,
                             cfg.subjects.population())
            s.meta["made_with"] = stamp
            save_subject(s, path)
            _log(f"subject {path.stem}: height {s.meta['height_m']:.2f} m, fit {s.meta['registration']['fit_mean_mm']:.1f} mm ({time.time() - t0:.0f} s)")
            paths.append(path)
    else:
        from synth.scans import import_scans

        subjects, skipped_pairs = import_scans(model, Path(cfg.subjects.folder), skip_bad=cfg.skip_bad)
        skipped = [{"subject": n, "reason": r} for n, r in skipped_pairs]
        for s in subjects:
            paths.append(save_subject(s, folder / f"{s.id}.npz"))
        if not paths:
            raise ValueError(f"{cfg.subjects.folder}: no usable scan")
    index = {"subjects": {p.stem: sha256_file(p) for p in paths}, "skipped": skipped}
    with atomic_write(folder / "index.json", "w", f"{os.getpid()}") as fh:
        fh.write(json.dumps(index, indent=1, sort_keys=True) + "\n")
    return paths


def subdivide(faces: np.ndarray, uv_faces: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Midpoint subdivision: face ``f`` becomes faces ``4f .. 4f + 3``.

    Returns:
        (S, 2) the two parent vertices of every new vertex (a vertex of the input is its own two
        parents), and (4F, 3) the new faces.
    """
    v = int(faces.max()) + 1
    edges = np.sort(faces[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 3, 2), axis=2).reshape(-1, 2)
    uniq, inv = np.unique(edges, axis=0, return_inverse=True)
    mid = v + inv.reshape(-1, 3)  # (F, 3): midpoints of edges ab, bc, ca
    a, b, c = faces.T
    ab, bc, ca = mid.T
    new = np.stack([np.stack([a, ab, ca], 1), np.stack([ab, b, bc], 1), np.stack([ca, bc, c], 1), np.stack([ab, bc, ca], 1)], 1)
    parents = np.concatenate([np.stack([np.arange(v), np.arange(v)], 1), uniq])
    return parents, new.reshape(-1, 3)


# ------------------------------------------------------------------------------------------------
# Poses


class PoseSource:
    """Draws a pose (x, global orientation) from the prior or the motion library."""

    def __init__(self, cfg: GeneratorConfig) -> None:
        from blsm.mocap.prior import DEFAULT_PRIOR, load_prior

        self.cfg = cfg.poses
        self.prior_path = self.cfg.prior or DEFAULT_PRIOR
        self.prior = load_prior(self.prior_path)
        self.checker = None
        if self.cfg.plausible and self.cfg.source != "library":
            import blsm
            from blsm.mocap.plausible import PoseChecker

            self.checker = PoseChecker(blsm.load())
        self.clips: list[Any] = []
        if self.cfg.source != "prior":
            from blsm.mocap.library import list_clips, load_clip

            files = list_clips(self.cfg.library)
            names = {Path(f).stem for f in files}
            unknown = [n for n in (*self.cfg.clips, *self.cfg.exclude_clips, *self.cfg.child_clips) if n not in names]
            if unknown:
                raise ValueError(f"{self.cfg.library}: the motion library has no clip {unknown[0]!r}")
            if self.cfg.clips:
                files = [f for f in files if Path(f).stem in self.cfg.clips]
            files = [f for f in files if Path(f).stem not in self.cfg.exclude_clips]
            if not files:
                raise ValueError(f"{self.cfg.library}: the motion library holds no clips (after clips/exclude_clips)")
            self.clips = [load_clip(f) for f in files]
            kept = {c.name for c in self.clips}
            left_out = [n for n in self.cfg.child_clips if n not in kept]
            if left_out:
                raise ValueError(f"{self.cfg.library}: poses.child_clips names {left_out[0]!r}, which clips/exclude_clips leave out")
        self.child_clips = [i for i, c in enumerate(self.clips) if c.name in self.cfg.child_clips]

    def sample(self, rng: np.random.Generator, child: bool = False) -> tuple[np.ndarray, np.ndarray, dict]:
        """A pose for one person; ``child`` (younger than 18) restricts library frames to
        ``poses.child_clips`` where the config names them."""
        use_lib = self.cfg.source == "library" or (self.cfg.source == "mix" and rng.uniform() < self.cfg.library_rate)
        if use_lib:
            if child and self.child_clips:
                ci = self.child_clips[int(rng.integers(len(self.child_clips)))]
            else:
                ci = int(rng.integers(len(self.clips)))
            clip = self.clips[ci]
            fr = int(rng.integers(clip.num_frames))
            return clip.pose[fr].astype(np.float32), clip.global_orient[fr].astype(np.float32), {"source": "library", "clip": clip.name, "frame": fr}
        for redraws in range(self.cfg.max_redraws + 1):
            g = torch.Generator().manual_seed(int(rng.integers(2**62)))
            x = self.prior.sample(1, g)[0].numpy().astype(np.float32)
            if self.checker is None:
                return x, np.zeros(3, np.float32), {"source": "prior", "clip": "", "frame": -1}
            if self.checker.check(torch.from_numpy(x)[None]).plausible[0]:
                return x, np.zeros(3, np.float32), {"source": "prior", "clip": "", "frame": -1, "redraws": redraws}
        raise ValueError(
            f"{self.prior_path}: no plausible pose in {self.cfg.max_redraws + 1} draws "
            "(a prior of implausible poses; set poses.plausible: false to use it as drawn)"
        )


def place_people(footprints: list[tuple[np.ndarray, float]], gap: float, rng: np.random.Generator) -> list[np.ndarray]:
    """Horizontal offsets so that the people's footprint discs (centre, radius) stay ``gap`` apart."""
    placed: list[tuple[np.ndarray, float]] = []
    offsets = []
    for centre, r in footprints:
        pos = np.zeros(2)
        if placed:
            for _ in range(200):
                ang = rng.uniform(0, 2 * math.pi)
                ref, rr = placed[int(rng.integers(len(placed)))]
                pos = ref + (rr + r + gap + rng.uniform(0.0, 0.8)) * np.array([math.cos(ang), math.sin(ang)])
                if all(np.linalg.norm(pos - q) >= rq + r + gap for q, rq in placed):
                    break
            else:  # pragma: no cover - 8 people always fit in 200 tries
                raise RuntimeError("could not place the people apart")
        placed.append((pos, r))
        offsets.append(np.array([pos[0] - centre[0], 0.0, pos[1] - centre[1]]))
    return offsets


# ------------------------------------------------------------------------------------------------
# A worker's state


class SampleMaker:
    """Everything a worker needs to make samples: model, subjects, poses, backgrounds, scenes."""

    def __init__(self, cfg: GeneratorConfig, out: Path, variant: str, threads: int = 0) -> None:
        """``threads``: the worker's CPU threads, for the denoiser (0: all)."""
        import blsm

        self.cfg, self.out, self.variant, self.threads = cfg, Path(out), variant, threads
        self.model = blsm.load()
        index = json.loads((self.out / SUBJECTS / "index.json").read_text())
        self.subjects: list[Subject] = [load_subject(self.out / SUBJECTS / f"{k}.npz") for k in sorted(index["subjects"])]
        self.poses = PoseSource(cfg)
        m = self.model
        self.bone_to_part = lab.bone_parts(m.vertex_bones.numpy(), m.vertex_parts.numpy(), m.num_joints)
        self.regions = lab.keypoint_regions(m.keypoint_joint.numpy(), m.keypoint_vertices.numpy(), m.vertex_bones.numpy(), m.parents)
        self.is_joint = m.keypoint_joint.numpy() >= 0
        b = cfg.background
        self.bg_files = []
        if b.kind == "hdri":
            self.bg_files = bg.list_folder(b.folder, bg.HDRI_EXT, "HDRI", b.files, b.exclude)
        elif b.kind == "images":
            self.bg_files = bg.list_folder(b.folder, bg.IMAGE_EXT, "background image", b.files, b.exclude)
        self.horizons = bg.read_horizons(b.folder) if b.kind == "images" and b.align_horizon else {}
        # Hair is grown on Anny's stand-in people only: user scans carry their own.
        self.hair = cfg.hair.enabled and cfg.pipeline != "raw" and cfg.subjects.source == "anny"
        # With the backdrop composited, the path tracer renders only the people's window
        # (synth.render.people_window, passed to the kernel as data: no compile per image).
        # False renders whole frames (tests and benchmarks compare).
        self.windowed = True
        self.head_bone = list(m.bone_names).index("head")
        self._bg_cache: dict[Path, np.ndarray] = {}
        self._rigs: dict[int, dict[str, Any]] = {}
        self._renderers: dict[tuple, PeopleRenderer] = {}
        self._sequences: Any = None

    def sequences(self) -> Any:
        """This worker's :class:`synth.sequence.SequenceMaker` (made on first use)."""
        if self._sequences is None:
            from synth.sequence import SequenceMaker

            self._sequences = SequenceMaker(self)
        return self._sequences

    # -- per subject, cached: render mesh, linear texture, face bones
    def rig(self, si: int) -> dict[str, Any]:
        if si in self._rigs:
            return self._rigs[si]
        s, m, pipe = self.subjects[si], self.model, self.cfg.pipeline
        if pipe == "blsm":
            from synth.transfer import transfer_texture

            faces, uv, fuv = m.faces.numpy(), m.uvs.numpy(), m.faces_uv.numpy()
            tex = transfer_texture(s, m, min(self.cfg.subjects.texture_size, 1024))
            weights = m.weights.numpy()
            parents = None
            if self.cfg.subdivide:
                parents, faces_new = subdivide(faces)
                uvp, fuv = subdivide(fuv)
                uv = 0.5 * (uv[uvp[:, 0]] + uv[uvp[:, 1]])
                weights = 0.5 * (weights[parents[:, 0]] + weights[parents[:, 1]])
                faces = faces_new
        else:
            faces, uv, fuv, tex, weights, parents = s.faces, s.uv, s.faces_uv, s.texture, s.weights, None
        rig = {
            "mesh": RenderMesh.build(faces, uv, fuv),
            "faces": faces,
            "texture": srgb_to_linear(tex.astype(np.float32) / 255.0),
            "face_bones": lab.face_bones(faces, weights),
            "parents": parents,
        }
        if self.hair:
            from dataclasses import asdict

            from synth.hair import subject_hair, subject_hair_spec

            spec = subject_hair_spec(s, asdict(self.cfg.hair.styles), self.cfg.seed)
            rig["hair"] = (spec, subject_hair(s, m, spec, pipe))
        self._rigs[si] = rig
        return rig

    def background(self, rng: np.random.Generator, camera: Any) -> bg.Background:
        b, cam = self.cfg.background, self.cfg.camera
        scale = float(2.0 ** rng.uniform(*b.exposure_ev))
        rot = float(rng.uniform(0, 2 * math.pi))
        if b.kind == "hdri":
            f = self.bg_files[int(rng.integers(len(self.bg_files)))]
            if f not in self._bg_cache:
                self._bg_cache[f] = bg.load_hdri(f, b.env_width)
            return bg.Background("hdri", self._bg_cache[f], rot, scale, None, {"file": f.name, "rotation": rot, "exposure": scale})
        env, info = bg.procedural_sky(b.env_width, rng)
        if b.kind == "images":
            f = self.bg_files[int(rng.integers(len(self.bg_files)))]
            if f not in self._bg_cache:
                self._bg_cache[f] = bg.read_image(f)
            extra: dict[str, Any] = {}
            plate = None
            if self.horizons:  # a described bank: the plate's horizon on the camera's (plates.json)
                hz = self.horizons.get(f.name)
                row = bg.horizon_row(camera.K, camera.R) if hz is not None else None
                if row is not None:
                    plate = bg.crop_backplate_at_horizon(self._bg_cache[f], hz, cam.width, cam.height, row, rng)
                extra = {"horizon_row": row if plate is not None else None}
            if plate is None:
                plate = bg.crop_backplate(self._bg_cache[f], cam.width, cam.height, rng)
            return bg.Background("images", env, rot, scale, plate,
                                 {"file": f.name, "rotation": rot, "exposure": scale, **info, **extra})
        return bg.Background("default", env, rot, scale, None, {"rotation": rot, "exposure": scale, **info})

    def renderer(self, meshes: list[RenderMesh], textures: list[np.ndarray], backplate: bool) -> PeopleRenderer:
        """The scene for these people's meshes. People of one topology and texture size (every
        Anny subject; the blsm pipeline always) share one scene of ``people.max`` slots, the
        unused ones hidden, so a worker compiles its kernels once for any people count; people of
        several topologies (scans, raw pipeline) get a scene per combination."""
        slots, shapes = meshes, [t.shape[:2] for t in textures]
        if len({m.key for m in meshes}) == 1 and len(set(shapes)) == 1:
            slots, shapes = [meshes[0]] * self.cfg.people.max, [shapes[0]] * self.cfg.people.max
        key = (tuple(m.key for m in slots), tuple(shapes), backplate)
        r = self._renderers.get(key)
        if r is None:
            if len(self._renderers) >= 4:
                self._renderers.pop(next(iter(self._renderers)))
            cam, b = self.cfg.camera, self.cfg.background
            r = PeopleRenderer(
                slots, shapes, cam.width, cam.height,
                env_shape=(b.env_width // 2, b.env_width), variant=self.variant,
                max_depth=self.cfg.render.max_depth, backplate=backplate,
                denoise=self.cfg.render.denoise, denoise_threads=self.threads, hair=self.hair,
                sampler=self.cfg.render.sampler, denoise_quality=self.cfg.render.denoise_quality,
            )  # fmt: skip
            self._renderers[key] = r
        return r

    def make(self, index: int, rng: np.random.Generator) -> dict[str, bytes]:
        cfg = self.cfg
        n = int(rng.integers(cfg.people.min, cfg.people.max + 1))
        people = [self.pose_person(rng) for _ in range(n)]
        shells = [self.shell(p) for p in people]
        hulls = [outline_index(v) for v in shells]
        foot = []
        for v, idx in zip(shells, hulls):
            xz = v[idx][:, [0, 2]]
            c = 0.5 * (xz.min(0) + xz.max(0))
            foot.append((c, float(np.linalg.norm(xz - c, axis=1).max())))
        for p, v, idx, d in zip(people, shells, hulls, place_people(foot, cfg.people.gap, rng)):
            d = d - np.array([0.0, p["vertices"][:, 1].min(), 0.0])  # the body's feet on the floor y = 0
            move_person(p, d)
            p["outline"] = (v[idx] + d).astype(np.float32)
        outline = np.concatenate([p["outline"] for p in people])  # every person's hull vertices
        camera, cam_info = sample_camera(outline, cfg.camera, rng)
        back = self.background(rng, camera)
        frame, labels = self.render_frame(index, people, camera, cam_info, back, rng)
        return self.encode(index, camera, cam_info, back, people, frame, labels)

    def pose_person(self, rng: np.random.Generator) -> dict[str, Any]:
        """A subject drawn and posed by the pose source (at the origin, before placement)."""
        si = int(rng.integers(len(self.subjects)))
        s = self.subjects[si]
        age = s.meta.get("phenotype", {}).get("age_years")
        x, orient, motion = self.poses.sample(rng, child=age is not None and age < 18.0)
        p = self.pose(si, x, orient, np.zeros(3, np.float32))
        p["motion"] = motion
        return p

    def pose(self, si: int, x: np.ndarray, orient: np.ndarray, transl: np.ndarray) -> dict[str, Any]:
        """Subject ``si`` posed (:func:`synth.subjects.pose_subject`), subdivided as its render mesh
        is, with its hair posed; ``rig`` and ``subject`` attached."""
        s = self.subjects[si]
        p = pose_subject(s, self.model, {"pose": x, "global_orient": orient, "transl": transl}, self.cfg.pipeline)
        rig = self.rig(si)
        if rig["parents"] is not None:
            par = rig["parents"]
            p["vertices"] = 0.5 * (p["vertices"][par[:, 0]] + p["vertices"][par[:, 1]])
        if "hair" in rig:
            from synth.hair import pose_hair

            p["hair"] = pose_hair(rig["hair"][1], p["transforms"])
        p.update(subject=s.id, si=si, rig=rig)
        return p

    @staticmethod
    def shell(p: dict[str, Any]) -> np.ndarray:
        """The person's posed vertices with the hair's: footprints, framing and boxes use their hull
        vertices, which hold the extremes (:func:`synth.camera.outline_index`)."""
        return p["vertices"] if "hair" not in p else np.concatenate([p["vertices"], p["hair"]])

    def render_frame(self, index: int, people: list[dict[str, Any]], camera: Any, cam_info: dict, back: bg.Background,
                     rng: np.random.Generator) -> tuple[Any, dict[str, Any]]:
        """Render the placed ``people`` (each with its ``outline``) and make their labels."""
        cfg = self.cfg
        outline = np.concatenate([p["outline"] for p in people])
        rigs = [p["rig"] for p in people]
        # With the shadow catcher or a thin lens the environment is hidden from the camera (as behind
        # a backplate) and the backdrop is composited after the render: darkened by the people's
        # shadows, blurred by the lens.
        composite = cfg.ground.shadows or "f_number" in cam_info
        r = self.renderer([q["mesh"] for q in rigs], [q["texture"] for q in rigs], back.backplate is not None or composite)
        seed = int(rng.integers(2**31))
        frame = r.render(
            [p["vertices"] for p in people], [q["texture"] for q in rigs], camera,
            back.env, back.rotation, back.scale, None if composite else back.backplate, cfg.render.spp, seed,
            [(p["hair"], q["hair"][1].colours) for p, q in zip(people, rigs)] if self.hair else None,
            # Composited, the backdrop is not path traced: only the people's window is.
            people_window(camera, outline) if composite and self.windowed else None,
        )  # fmt: skip
        if composite:
            self._composite_backdrop(r, frame, camera, cam_info, back, outline, rng)
        labels = lab.person_labels(
            frame, camera,
            [{"vertices": p["vertices"], "outline": p["outline"], "faces": q["faces"], "face_bones": q["face_bones"],
              "keypoints": p["keypoints"], **self._hair_labels(p)} for p, q in zip(people, rigs)],
            self.bone_to_part, self.regions, self.is_joint,
        )  # fmt: skip
        if labels["unassigned"]:
            raise RuntimeError(f"sample {index}: {labels['unassigned']} hit pixels belong to no person's face")
        return frame, labels

    def _hair_labels(self, p: dict[str, Any]) -> dict[str, Any]:
        if "hair" not in p:
            return {}
        from synth.hair import hair_faces

        return {"hair_vertices": p["hair"], "hair_faces": hair_faces(), "hair_bone": self.head_bone}

    def _composite_backdrop(self, r: PeopleRenderer, frame: Any, camera: Any, cam_info: dict, back: bg.Background,
                            outline: np.ndarray, rng: np.random.Generator) -> None:
        """Composite the backdrop behind the people (``outline``: their hull vertices): darkened where
        they shadow the ground (:mod:`synth.ground`, with ``ground.shadows``), blurred by the thin
        lens (:mod:`synth.lens`, with ``camera.f_number``). Records what it did in ``back.info``."""
        from synth import ground, lens

        g = self.cfg.ground
        backdrop = back.backplate
        if backdrop is None:  # the environment seen by the camera, evaluated by the scene's own envmap
            backdrop = ground.emitter_backdrop(r.mi, r.environment, camera,
                                               ground.backdrop_supersampling(camera, back.env.shape[1]))
        if g.shadows:
            pts = outline.astype(np.float64)
            centre = 0.5 * (pts.min(0) + pts.max(0))
            sphere = (centre, float(np.linalg.norm(pts - centre, axis=1).max()) + 0.01)
            ratio, on_ground = ground.shadow_ratio(
                ground.mitsuba_ray_test(r.mi, r.scene), camera, back.env, back.rotation, sphere,
                np.random.default_rng(int(rng.integers(2**63))),
                samples=g.samples, max_distance=g.max_distance, exclude=frame.alpha >= 1.0,
            )  # fmt: skip
            backdrop = backdrop * ratio[..., None]
            back.info["ground"] = {"shadow_catcher": True, "ground_pixels": int(on_ground.sum()),
                                   "shadowed_pixels": int((ratio < 0.95).sum())}  # fmt: skip
        if "f_number" in cam_info:
            f_px = float(camera.K[0, 0])
            aperture = cam_info["focal_mm"] / cam_info["f_number"] / 1000.0
            on, pts = ground.ground_points(camera, np.inf)
            depth = np.full(on.shape, np.inf)
            depth[on] = (pts[on] @ camera.R.T + camera.t)[:, 2]
            coc = lens.circle_of_confusion(depth, cam_info["focus_m"], f_px, aperture)
            backdrop = lens.defocus(backdrop, coc)
            back.info["lens"] = {"coc_px_max": round(float(coc.max()), 3), "coc_px_infinity": round(
                float(lens.circle_of_confusion(np.array([np.inf]), cam_info["focus_m"], f_px, aperture)[0]), 3)}
        frame.rgb = (frame.rgb + (1.0 - frame.alpha[..., None]) * backdrop).astype(np.float32)

    def encode(self, index, camera, cam_info, back, people, frame, labels, extra: dict[str, Any] | None = None,
               extra_people: list[dict[str, Any]] | None = None) -> dict[str, bytes]:
        """The sample's fields; ``extra`` adds top-level label keys and ``extra_people`` keys per
        person (a sequence's, :mod:`synth.sequence`)."""
        from blsm.joint_limits import unconstrained_from_angles

        m = self.model
        plist = []
        for p, lp in zip(people, labels["people"]):
            x = p["pose"]
            if x is None:  # raw: the scan's own angles
                x = unconstrained_from_angles(torch.as_tensor(p["angles"])[None], m.dof_limits)[0].numpy()
            lengths = _bone_lengths(p["rest_joints"], p["keypoints"], m)
            plist.append(
                {
                    "subject": p["subject"],
                    "pipeline": self.cfg.pipeline,
                    "motion": p["motion"],
                    **({"hair": p["rig"]["hair"][0].to_json()} if "hair" in p else {}),
                    "blsm": {
                        "pose": _l(x), "angles": _l(p["angles"]), "bone": _l(p["bone"]), "shape": _l(p["shape"]),
                        "global_orient": _l(p["global_orient"]), "transl": _l(p["transl"]),
                    },
                    "bone_lengths": _l(lengths),
                    "keypoints_3d": _l(p["keypoints"]),
                    "keypoints_3d_cam": _l(lp["keypoints_3d_cam"]),
                    "keypoints_2d": _l(lp["keypoints_2d"]),
                    "visible": [bool(v) for v in lp["visible"]],
                    "in_frame": [bool(v) for v in lp["in_frame"]],
                    "box": lp["box"],
                    "box_full": None if lp["box_full"] is None else _l(lp["box_full"]),
                    "pixels": lp["pixels"],
                    **(extra_people[len(plist)] if extra_people else {}),
                }
            )  # fmt: skip
        doc = {
            "format": fmt.FORMAT,
            "version": fmt.VERSION,
            "index": index,
            "seed": self.cfg.seed,
            "image": {"width": camera.width, "height": camera.height, "pixel_center": 0.5},
            "camera": {"K": _l(camera.K), "R": _l(camera.R), "t": _l(camera.t), "info": cam_info},
            "background": {"kind": back.kind, **{k: (v if not isinstance(v, float) else round(v, 6)) for k, v in back.info.items()}},
            "keypoint_names": list(m.keypoint_names),
            "bone_names": list(m.bone_names),
            "part_names": list(m.part_names),
            "people": plist,
        }
        extra = dict(extra or {})
        doc["camera"].update(extra.pop("camera", {}))
        doc.update(extra)
        rgb = np.round(linear_to_srgb(frame.rgb) * 255.0).astype(np.uint8)
        return {
            "rgb.png": fmt.encode_png(rgb),
            "json": fmt.encode_json(doc),
            "mask.png": fmt.encode_png(labels["mask"]),
            "parts.png": fmt.encode_png(labels["parts"], fmt.PART_PALETTE),
            "bones.png": fmt.encode_png(labels["bones"], fmt.BONE_PALETTE),
            "depth.exr": fmt.encode_exr(labels["depth"]),
            "corr.npy.gz": fmt.encode_npy_gz(labels["corr"]),
        }


def _l(a: Any) -> Any:
    """Array to nested lists of Python floats rounded to 1e-6 (stable JSON across runs; the
    precision the validator allows for is stated in :mod:`synth.format`)."""
    return fmt.json_round(a)


def _bone_lengths(rest_joints: np.ndarray, keypoints: np.ndarray, model: Any) -> np.ndarray:
    """Per bone, metres: head to its primary child's head in the person's bind pose; leaf bones
    (head, hands, feet) to their tip keypoint (head top, hand tip, toe tip)."""
    from blsm import skeleton

    names = model.bone_names
    tips = {"head": "head_top", "wrist_l": "hand_tip_l", "wrist_r": "hand_tip_r", "ankle_l": "toe_tip_l", "ankle_r": "toe_tip_r"}
    out = np.zeros(len(names))
    for j, name in enumerate(names):
        if name in tips:
            # Tips are posed points; the leaf bone's length is pose-independent (rigid bone).
            continue
        c = names.index(skeleton.PRIMARY_CHILD[name])
        out[j] = np.linalg.norm(rest_joints[c] - rest_joints[j])
    kp = list(model.keypoint_names)
    for name, tip in tips.items():
        j = names.index(name)
        out[j] = float(np.linalg.norm(keypoints[kp.index(tip)] - _posed_joint(keypoints, model, j)))
    return out


def _posed_joint(keypoints: np.ndarray, model: Any, j: int) -> np.ndarray:
    k = list(model.keypoint_joint.numpy()).index(j)
    return keypoints[k]


# ------------------------------------------------------------------------------------------------
# Workers and the run


_MAKER: SampleMaker | None = None
_ARGS: tuple = ()
_MADE = 0
_SEQUENCE: tuple[int, Any] = (-1, None)  # (sequence, its frames' fields or the exception that stopped it)


def frames_per_sample(cfg: GeneratorConfig) -> int:
    """Samples (frames) per unit of work: a sequence's frames, or 1 for single images."""
    return cfg.sequence.frames if cfg.sequence.enabled else 1


def run_writer(cfg: GeneratorConfig, out: Path, part: tuple[int, int] = (1, 1)) -> ShardWriter:
    """The shard writer of a run: ``num`` images, or ``num`` sequences of ``sequence.frames`` frames
    with ``sequence.per_shard`` whole sequences a shard (docs/video.md, Storage)."""
    n = frames_per_sample(cfg)
    size = cfg.sequence.per_shard * n if cfg.sequence.enabled else cfg.output.shard_size
    return ShardWriter(out, cfg.num * n, size, cfg.seed, config=_cfg_json(cfg), versions=versions(), part=part)


def _init_worker(cfg_dict: dict, out: str, variant: str, threads: int, pool_worker: bool = False) -> None:
    """Load a worker's state once: the model, subjects, poses, backgrounds (scenes on first use).

    A pool worker also limits numpy's BLAS and OpenMP pools to one thread: their arrays are small,
    and idle BLAS threads spinning after each call took about 100 ms of CPU per image from the
    other worker (measured: 337 ms of CPU for 239 ms of wall time per image, 242 ms with one
    thread).
    """
    global _MAKER, _ARGS, _MADE, _SEQUENCE
    import drjit as dr

    from synth.config import from_dict

    if pool_worker:
        from threadpoolctl import threadpool_limits

        threadpool_limits(limits=1)
    torch.set_num_threads(1)
    dr.set_thread_count(threads)
    _ARGS, _MADE, _SEQUENCE = (cfg_dict, out, variant, threads), 0, (-1, None)
    _MAKER = SampleMaker(from_dict(GeneratorConfig, cfg_dict), Path(out), variant, threads)


def _make_one(index: int) -> tuple[int, dict[str, bytes] | None, str, str]:
    """Sample ``index`` as ``(index, fields, "", "")``, or ``(index, None, error type, message)``.
    In a sequence run the worker makes a sequence's frames together when asked for its first and
    serves the others from them (the Ray engine asks for a shard's samples in order)."""
    global _SEQUENCE
    assert _MAKER is not None
    try:
        if not _MAKER.cfg.sequence.enabled:
            return index, _MAKER.make(index, sample_rng(_MAKER.cfg.seed, index)), "", ""
        seq, f = divmod(index, _MAKER.cfg.sequence.frames)
        if _SEQUENCE[0] != seq:
            _SEQUENCE = (seq, None)
            try:
                _SEQUENCE = (seq, _MAKER.sequences().make(seq, sequence_rng(_MAKER.cfg.seed, seq)))
            except Exception as exc:  # every frame of the sequence reports it
                _SEQUENCE = (seq, exc)
        if isinstance(_SEQUENCE[1], Exception):
            raise _SEQUENCE[1]
        return index, _SEQUENCE[1][f], "", ""
    except Exception as exc:  # reported by the main process: stop, or skip with --skip-bad
        return index, None, type(exc).__name__, format_error(exc)


def _make_sequence(seq: int) -> list[tuple[int, dict[str, bytes] | None, str, str]]:
    """Every frame of sequence ``seq`` (:func:`_make_one`), for the process pool: one task a sequence."""
    assert _MAKER is not None
    n = _MAKER.cfg.sequence.frames
    return [_make_one(i) for i in range(seq * n, (seq + 1) * n)]


def _make_in_process(index: int) -> tuple[int, dict[str, bytes] | None, str, str]:
    """:func:`_make_one` in this process, rebuilding the worker state every ``recycle_after`` images
    (at a sequence's first frame in a sequence run)."""
    global _MADE
    assert _MAKER is not None
    if _MADE >= _MAKER.cfg.render.recycle_after and index % frames_per_sample(_MAKER.cfg) == 0:
        _init_worker(*_ARGS)
    _MADE += 1
    return _make_one(index)


def generate(
    cfg: GeneratorConfig,
    out: str | Path,
    workers: int = 1,
    resume: bool = False,
    progress: bool = True,
    stop_after: int | None = None,
    on_image: Callable[[int], None] | None = None,
    part: tuple[int, int] = (1, 1),
    engine: str = "local",
    address: str | None = None,
    replace_stale: bool = False,
) -> dict[str, Any]:
    """Generate the dataset of ``cfg`` into ``out``; return the manifest.

    Worker processes make samples (any sample, from ``(seed, index)`` alone); this process writes
    them into shards in index order with :meth:`synth.shards.ShardWriter.run` (each shard to a
    temporary file renamed when complete, the manifest rewritten after every shard). Workers are replaced after ``render.recycle_after``
    images, which bounds any memory a long run might accumulate in them.

    Args:
        cfg: the configuration (``cfg.num`` samples).
        out: the dataset folder.
        workers: worker processes; 1 makes the samples in this process.
        resume: continue an interrupted run (keeps shards whose checksum matches).
        progress: report progress with rate and ETA on stderr.
        stop_after: stop after this many shards (tests).
        on_image: called in this process as ``on_image(images_done)`` after each image
            (benchmarks).
        part: ``(I, N)``: make only part ``I`` of ``N`` (:mod:`synth.shards`, Parts): its shards
            and ``manifest-part-I-of-N.json``; ``synth merge`` joins the parts.
        engine: ``"local"`` (a process pool of ``workers``) or ``"ray"`` (one Ray task per shard,
            :mod:`synth.engine_ray`; ``workers`` is not used).
        address: the Ray cluster to join (``engine="ray"``); None starts a local one.
        replace_stale: with ``resume``, a dataset in ``out`` made by another run (config, seed,
            count or shard size) is moved to a sibling folder by :func:`set_aside_stale` instead
            of refusing the run (``make demo`` after the defaults changed).

    Every input file (backgrounds, scans, poses) is opened and checked first; then the folder is
    locked (:mod:`synth.lock`: one writer per folder; temporary files carry the writer's tag). Bad
    input leaves no new file or folder behind.

    Raises:
        ValueError: bad input (config, subjects, backgrounds, poses), before any shard is written;
            the folder held by another run; a failed write (:class:`synth.shards.WriteError`, e.g.
            a full disk), with the finished shards kept for ``--resume``.
        RuntimeError: a sample failed (without ``cfg.skip_bad``); finished shards are kept.
    """
    import blsm

    if engine not in ENGINES:
        raise ValueError(f"unknown engine {engine!r}; choose one of {list(ENGINES)}")
    out = Path(out)
    writer = run_writer(cfg, out, part)
    if not writer.shards():
        raise ValueError(f"part {part[0]}/{part[1]} has no shards: the dataset has {writer.num_shards}")
    if not (resume and replace_stale):
        writer.pending(resume)  # fail fast (a dataset already there); checked again under the lock
    elif part != (1, 1):
        raise ValueError("replace_stale (--replace-stale) sets aside a whole dataset; it cannot be used with --part")
    model = blsm.load()
    check_inputs(cfg, model)
    if resume and replace_stale:
        aside = set_aside_stale(writer)
        if aside is not None:
            _log(f"{out}: held a dataset made with other settings; moved it to {aside}")
    variant = choose_variant(cfg)
    # The cluster is reached (or Ray found missing) before anything is made.
    with _ray_session(address) if engine == "ray" else contextlib.nullcontext():
        return _generate(cfg, out, writer, model, variant, workers, resume, progress, stop_after, on_image, part,
                         engine)


def set_aside_stale(writer: ShardWriter) -> Path | None:
    """Move what ``writer``'s folder holds to ``<folder>.stale-<UTC time>`` when its manifest
    describes another run (:meth:`synth.shards.ShardWriter.same_run`); return that folder, or None
    when there was nothing to move (no manifest, or the same run, which ``--resume`` continues).

    Nothing is deleted. The folder is locked for the move (:mod:`synth.lock`), so a run writing
    into it is never moved from under it; every entry but the lock files moves, and the folder stays
    (empty) for the new run. An unreadable manifest is not a run to set aside: it stays an error.
    """
    out = writer.out
    if not writer.manifest_path.exists():
        return None
    with out_lock.acquire(out, 1, 1, warn=_log):
        man = writer.read_manifest()
        if man is None:  # removed before the lock was taken
            return None
        try:
            writer.same_run(man, writer.manifest_path)
        except ValueError:  # another run's dataset (or not one of ours): moved, not refused
            pass
        else:
            return None
        stamp = time.strftime("%Y%m%dT%H%M%SZ", time.gmtime())
        aside = out.with_name(f"{out.name}.stale-{stamp}")
        n = 1
        while aside.exists():
            n += 1
            aside = out.with_name(f"{out.name}.stale-{stamp}-{n}")
        aside.mkdir()
        for entry in sorted(out.iterdir()):
            if not entry.name.startswith(out_lock.LOCK_PREFIX):
                entry.rename(aside / entry.name)
    return aside


@contextlib.contextmanager
def _ray_session(address: str | None) -> Iterator[None]:
    """Connected to the Ray cluster at ``address`` (:func:`synth.engine_ray.connect`) for the block;
    disconnected after it unless this process was connected before."""
    from synth.engine_ray import connect

    started = connect(address)
    try:
        yield
    finally:
        if started:
            import ray

            ray.shutdown()


def _generate(
    cfg: GeneratorConfig,
    out: Path,
    writer: ShardWriter,
    model: Any,
    variant: str,
    workers: int,
    resume: bool,
    progress: bool,
    stop_after: int | None,
    on_image: Callable[[int], None] | None,
    part: tuple[int, int],
    engine: str,
) -> dict[str, Any]:
    """:func:`generate` once its inputs are checked: lock, subjects, shards."""
    created = _first_missing(out)
    try:
        out.mkdir(parents=True, exist_ok=True)
        lock = out_lock.acquire(out, *part, warn=_log, stale_files=writer.temporary_files)
    except OSError as exc:
        _remove(created)
        raise WriteError.of(Path(exc.filename or out), exc) from None
    except BaseException:
        _remove(created)
        raise
    with lock:
        writer.tag = lock.tag
        new_subjects = not (out / SUBJECTS).exists()
        try:
            todo, done, skipped = writer.pending(resume)
            if part[1] > 1:  # parts running side by side make the subjects once
                with out_lock.exclusive(out / SUBJECTS_LOCK, lambda: _log("waiting for another part to make the subjects")):
                    prepare_subjects(cfg, out, model)
            else:
                prepare_subjects(cfg, out, model)
        except (ValueError, OSError) as exc:
            # Bad input found before any shard: leave the folder as it was.
            lock.release()
            _remove(created if created is not None else out / SUBJECTS if new_subjects else None)
            if isinstance(exc, OSError):
                raise WriteError.of(Path(exc.filename or out / SUBJECTS), exc) from None
            raise
        if engine == "ray":
            from synth.engine_ray import Worker, run_ray

            todo = todo[:stop_after] if stop_after is not None else todo
            meter = _Progress(sum(len(writer.indices(s)) for s in todo), progress)
            man = run_ray(cfg, _cfg_json(cfg), out, writer, (todo, done, skipped), variant,
                          Worker(_init_worker, _make_one, _log), meter, on_image)
            _log_done(man, meter)
            return man
        return _run(cfg, out, writer, (todo, done, skipped), variant, workers, progress, stop_after, on_image)


def merge(out: str | Path) -> dict[str, Any]:
    """``synth merge DIR``: join the parts of a partitioned run (:func:`synth.shards.merge_parts`)
    under the folder's lock (refused while a part still runs); return the manifest."""
    from synth.shards import merge_parts

    out = Path(out)
    if not out.is_dir():
        raise ValueError(f"{out}: no such dataset folder")
    with out_lock.acquire(out, warn=_log) as lock:
        man = merge_parts(out, lock.tag)
        (out / SUBJECTS_LOCK).unlink(missing_ok=True)
    return man


def check_inputs(cfg: GeneratorConfig, model: Any) -> None:
    """Open and check every input file of a run before any work: the pose source (for sequences, clips
    long enough), every background file (decoded as the workers will) and every scan folder; a
    ValueError names the first bad one."""
    poses = PoseSource(cfg)
    if cfg.sequence.enabled:
        from synth.sequence import eligible_clips

        eligible_clips(cfg, poses.clips, model.dof_limits.numpy())
    b = cfg.background
    if b.kind == "hdri":
        bg.check_files(bg.list_folder(b.folder, bg.HDRI_EXT, "HDRI", b.files, b.exclude), b.kind, b.env_width)
    elif b.kind == "images":
        bg.check_files(bg.list_folder(b.folder, bg.IMAGE_EXT, "background image", b.files, b.exclude), b.kind, b.env_width)
        if b.align_horizon:
            bg.read_horizons(b.folder)  # a bad plates.json is an error before any work
    if cfg.subjects.source == "folder":
        from synth.scans import check_scans

        check_scans(model, Path(cfg.subjects.folder), skip_bad=cfg.skip_bad)


def _first_missing(path: Path) -> Path | None:
    """The outermost folder of ``path`` that does not exist yet (what ``mkdir -p`` would make)."""
    missing = None
    for p in (path, *path.parents):
        if p.exists():
            break
        missing = p
    return missing


def _remove(path: Path | None) -> None:
    if path is not None and path.exists():
        shutil.rmtree(path, ignore_errors=True)


def _run(
    cfg: GeneratorConfig,
    out: Path,
    writer: ShardWriter,
    plan: tuple[list[int], dict[str, Any], list[dict[str, Any]]],
    variant: str,
    workers: int,
    progress: bool,
    stop_after: int | None,
    on_image: Callable[[int], None] | None,
) -> dict[str, Any]:
    """The shards of :func:`generate`, once its inputs are checked and its lock is held."""
    todo, done, skipped = plan
    if stop_after is not None:
        todo = todo[:stop_after]
    indices = [i for s in todo for i in writer.indices(s)]
    workers = max(1, min(workers, -(-len(indices) // frames_per_sample(cfg))))
    plural = "s" * (workers > 1)
    _log(f"{len(indices)} images in {len(todo)} shards -> {out} ({workers} worker{plural}, Mitsuba {variant})")
    meter = _Progress(len(indices), progress)
    init = (_cfg_json(cfg), str(out), variant, max(1, (os.cpu_count() or 1) // workers))
    pool = None
    if not indices:  # a resumed run that is already complete: nothing to load
        results = iter(())
    elif workers == 1:
        _init_worker(*init)
        results = map(_make_in_process, indices)
    elif cfg.sequence.enabled:  # a task a sequence, so that one worker makes all its frames
        n = cfg.sequence.frames
        pool = mp.get_context("spawn").Pool(workers, _init_worker, (*init, True),
                                            maxtasksperchild=max(1, cfg.render.recycle_after // n))
        results = itertools.chain.from_iterable(pool.imap(_make_sequence, sorted({i // n for i in indices})))
    else:
        pool = mp.get_context("spawn").Pool(workers, _init_worker, (*init, True), maxtasksperchild=cfg.render.recycle_after)
        results = pool.imap(_make_one, indices)

    def make_sample(i: int, rng: np.random.Generator) -> dict[str, bytes]:
        # The samples come from the workers, in index order; each worker drew this same rng itself.
        index, fields, kind, msg = next(results)
        assert index == i
        meter.tick()
        if on_image is not None:
            on_image(meter.made)
        if fields is not None:
            return fields
        if cfg.skip_bad:
            raise SkipSample(f"{kind}: {msg}")
        raise RuntimeError(f"sample {i}: {msg}")

    shards_done = len(done)

    def on_shard(s: int, count: int) -> None:
        nonlocal shards_done
        shards_done += 1
        meter.shard(writer.progress_line(s, count, shards_done))

    # In this process (one worker), numpy's BLAS keeps one thread while samples are made: its idle
    # threads would otherwise spin on the cores Dr.Jit renders with (see _init_worker).
    from threadpoolctl import threadpool_limits

    try:
        with threadpool_limits(limits=1) if pool is None else contextlib.nullcontext():
            man = writer.run(make_sample, on_shard=on_shard, plan=(todo, done, skipped))
    finally:
        if pool is not None:
            pool.terminate()
            pool.join()
    meter.close()
    _log_done(man, meter)
    return man


def _log_done(man: dict[str, Any], meter: _Progress) -> None:
    n, lost = sum(e["samples"] for e in man["shards"].values()), len(man["skipped"])
    _log(f"done: {n} samples in {len(man['shards'])} shards, {_hms(meter.elapsed())}" + (f", {lost} skipped" if lost else ""))


class _Progress:
    """Images done, rate and ETA on stderr: one updating line on a terminal, a line every 30 s
    (and one per shard) otherwise."""

    def __init__(self, total: int, enabled: bool) -> None:
        self.total, self.enabled, self.made = total, enabled, 0
        self.t0 = self.last = time.time()
        self.tty = sys.stderr.isatty()

    def elapsed(self) -> float:
        return time.time() - self.t0

    def line(self) -> str:
        rate = self.made / max(self.elapsed(), 1e-9)
        eta = (self.total - self.made) / rate if rate > 0 else float("nan")
        pct = 100.0 * self.made / max(self.total, 1)
        return f"{self.made}/{self.total} images ({pct:.0f} %)  {rate:.2f} img/s  ETA {_hms(eta)}"

    def tick(self) -> None:
        self.made += 1
        if not self.enabled:
            return
        if self.tty:
            print(f"\r[synth] {self.line()}   ", end="", file=sys.stderr, flush=True)
        elif time.time() - self.last >= 30:
            self.last = time.time()
            _log(self.line())

    def shard(self, msg: str) -> None:
        if self.enabled and not self.tty:
            _log(f"{msg}; {self.line()}")

    def close(self) -> None:
        if self.enabled and self.tty:
            print(file=sys.stderr, flush=True)


def _cfg_json(cfg: GeneratorConfig) -> dict:
    """The config as the manifest stores it. ``background.align_horizon`` is left out where it
    changes nothing (no plates.json horizons), so that runs made before it resume."""
    d = json.loads(json.dumps(asdict(cfg)))
    if not cfg.sequence.enabled:  # single images: the manifests of before
        d.pop("sequence")
    b = cfg.background
    if b.kind != "images" or not bg.read_horizons(b.folder):
        d["background"].pop("align_horizon")
    return d


def _hms(s: float) -> str:
    if not math.isfinite(s):
        return "--"
    s = int(s)
    return f"{s // 3600}h{s % 3600 // 60:02d}m" if s >= 3600 else f"{s // 60}m{s % 60:02d}s"


def format_error(exc: BaseException) -> str:
    """One line for the command line."""
    return str(exc).splitlines()[0] if str(exc) else type(exc).__name__



