"""Making one sample: a :class:`Scene` drawn (people drawn, posed and placed, a camera, a background,
occluders), then rendered, labelled and encoded.

A worker's :class:`SampleMaker` makes any sample from ``(seed, index)`` alone, in this order:

1. **People.** Each draws a subject not yet in the image (:func:`synth.people.draw_subject`) and a pose
   (:class:`synth.poses.PoseSource`: the pose prior or the motion library) and is posed
   (:func:`pose_person`, which ``synth validate`` uses to rebuild the same meshes) into a :class:`Person`.
2. **Placement** (:func:`synth.people.place_people`): footprint discs ``people.gap`` apart, feet on the ground.
3. **Camera and background** (:func:`synth.camera.sample_camera`, the background kind's draw:
   :mod:`synth.backgrounds`), then the occluders and seats: steps 1-3 are
   :meth:`SampleMaker.draw_scene`, which returns the :class:`Scene`.
4. **Render** (:meth:`SampleMaker.render`): the people's scene (:class:`synth.render.PeopleRenderer`,
   one per mesh topology, updated in place), the backdrop composited behind them with their shadows
   and the lens's blur; **labels** (:meth:`SampleMaker.labels`, :func:`synth.labels.person_labels`).
5. **Encoding** (:meth:`SampleMaker.encode`): the sample's fields (:mod:`synth.dataset.format`).

Sequences (:class:`synth.sequence.SequenceMaker`, built on a worker's sample maker) make a
:class:`Scene` per frame and reuse steps 4 and 5.
"""

from __future__ import annotations

import json
import math
from collections.abc import Sequence
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
import torch

from blsm.color import linear_to_srgb, srgb_to_linear
from synth import labels as lab
from synth.backgrounds import Background, background_kind
from synth.camera import facing_yaw_deg, outline_index, sample_camera
from synth.config import GeneratorConfig
from synth.dataset import format as fmt
from synth.people import draw_subject, footprint, place_people
from synth.poses import PoseSource
from synth.postures import seats
from synth.render import PeopleRenderer, RenderMesh, people_window
from synth.subjects import Subject, load_subject, pose_subject

if TYPE_CHECKING:
    from synth.garments import GarmentMesh, GarmentSpec
    from synth.hair import HairMesh, HairSpec

SUBJECTS = "subjects"
"""The dataset's folder of subjects (``DIR/subjects/*.npz`` and ``index.json``)."""


# ------------------------------------------------------------------------------------------------
# People


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


@dataclass(frozen=True, eq=False)
class Rig:
    """A subject as a worker renders it, made once per worker (:meth:`SampleMaker.rig`).

    Attributes:
        mesh: the render mesh (split at UV seams).
        faces: (F, 3) the faces of the posed vertices (after ``parents``' subdivision).
        texture: (H, W, 3) float32 linear albedo.
        face_bones: (F,) each face's bone (:func:`synth.labels.face_bones`).
        parents: (S, 2) the parent vertices of the subdivided mesh (:func:`subdivide`; the
            ``blsm`` pipeline with ``subdivide``), else None.
        hair_spec: the subject's hair (:mod:`synth.hair`), or None without hair.
        hair: that hair grown on the subject's rest body, or None.
        garment_spec, garments: the subject's clothing geometry (:mod:`synth.garments`) and its
            rest meshes, or None; ``weights`` (V, J) the body's LBS weights the layer is posed with.
    """

    mesh: RenderMesh
    faces: np.ndarray
    texture: np.ndarray
    face_bones: np.ndarray
    parents: np.ndarray | None
    hair_spec: HairSpec | None = None
    hair: HairMesh | None = None
    garment_spec: GarmentSpec | None = None
    garments: GarmentMesh | None = None
    weights: np.ndarray | None = None


@dataclass(eq=False)
class Person:
    """One posed person (metres; Y up, the ground at ``y = 0`` once placed).

    Attributes:
        subject: the subject's id.
        vertices: (V, 3) float32 posed vertices of the rendered mesh (subdivided as it is).
        faces: (F, 3) their faces.
        vertex_bones: (V,) each vertex's dominant bone.
        keypoints: (K, 3) and ``joints`` (J, 3): the registration's in this pose.
        angles: (47,) joint angles, radians; ``bone_scales`` (J,); ``rest_joints`` (J, 3) the bind
            pose's joints; ``transforms`` (J, 3, 4) the skinning transforms.
        pose: (47,) the unconstrained values x; None in the ``raw`` pipeline (the scan's own pose,
            ``angles``).
        global_orient, transl: (3,) the root's rotation vector and translation; ``bone`` and
            ``shape`` the subject's coefficients.
        hair: (H, 3) float32 posed hair vertices (:mod:`synth.hair`), or None.
        cloth, skirt: (V, 3) the posed cloth layer and (S, 3) skirt (:mod:`synth.garments`), or None.
        motion: where the pose came from (the label's ``motion``).
        si: the subject's index among the worker's subjects (-1 when rebuilt by ``validate``).
        rig: the subject's :class:`Rig` (None when rebuilt by ``validate``).
        outline: (N, 3) float32 hull vertices of body and hair, placed (None before placement).
    """

    subject: str
    vertices: np.ndarray
    faces: np.ndarray
    vertex_bones: np.ndarray
    keypoints: np.ndarray
    joints: np.ndarray
    angles: np.ndarray
    bone_scales: np.ndarray
    rest_joints: np.ndarray
    transforms: np.ndarray
    pose: np.ndarray | None
    global_orient: np.ndarray
    transl: np.ndarray
    bone: np.ndarray
    shape: np.ndarray
    hair: np.ndarray | None = None
    cloth: np.ndarray | None = None
    skirt: np.ndarray | None = None
    motion: dict[str, Any] = field(default_factory=dict)
    si: int = -1
    rig: Rig | None = None
    outline: np.ndarray | None = None

    def move(self, d: np.ndarray) -> None:
        """Translate the posed person (vertices, keypoints, joints, hair, root and the ``outline``
        once there is one) by ``d`` (3,) metres."""
        self.vertices = (self.vertices + d).astype(np.float32)
        self.keypoints = (self.keypoints + d).astype(np.float32)
        self.joints = (self.joints + d).astype(np.float32)
        if self.hair is not None:
            self.hair = (self.hair + d).astype(np.float32)
        if self.cloth is not None:
            self.cloth = (self.cloth + d).astype(np.float32)
        if self.skirt is not None:
            self.skirt = (self.skirt + d).astype(np.float32)
        self.transl = (self.transl + d).astype(np.float32)
        if self.outline is not None:
            self.outline = (self.outline + d).astype(np.float32)

    def shell(self) -> np.ndarray:
        """The posed vertices with the hair's and the clothes': footprints, framing and boxes use
        their hull vertices, which hold the extremes (:func:`synth.camera.outline_index`)."""
        parts = [a for a in (self.vertices, self.hair, self.cloth, self.skirt) if a is not None]
        return parts[0] if len(parts) == 1 else np.concatenate(parts)


def pose_person(
    subject: Subject,
    model: Any,
    pipeline: str,
    x: np.ndarray,
    orient: np.ndarray,
    transl: np.ndarray,
    subdivision: tuple[np.ndarray, np.ndarray] | None = None,
    hair: HairMesh | None = None,
    garments: tuple[GarmentMesh, np.ndarray] | None = None,
) -> Person:
    """``subject`` posed (:func:`synth.subjects.pose_subject`), subdivided as its render mesh is,
    with its hair posed: what the generator renders and ``synth validate`` rebuilds.

    Args:
        subject: the subject.
        model: the BLSM model.
        pipeline: ``rigged``, ``raw`` or ``blsm`` (:data:`synth.subjects.PIPELINES`).
        x: (47,) unconstrained pose values; ``orient`` (3,) the root's rotation vector, ``transl``
            (3,) its translation, metres (all three ignored by ``raw``).
        subdivision: :func:`subdivide`'s ``(parents, faces)`` of the render mesh, or None.
        hair: the subject's hair in the rest frame, or None.
        garments: the subject's clothes in the rest frame (:mod:`synth.garments`) and the body's
            (V, J) weights, or None.
    """
    p = pose_subject(subject, model, {"pose": x, "global_orient": orient, "transl": transl}, pipeline)
    vertices, faces, bones = p["vertices"], p["faces"], np.asarray(p["vertex_bones"])
    if subdivision is not None:
        par, faces = subdivision
        vertices = 0.5 * (vertices[par[:, 0]] + vertices[par[:, 1]])
        bones = bones[par[:, 0]]
    posed_hair = None
    if hair is not None:
        from synth.hair import pose_hair

        posed_hair = pose_hair(hair, p["transforms"])
    cloth = skirt = None
    if garments is not None:
        from synth.garments import pose_garments

        cloth, skirt = pose_garments(garments[0], garments[1], p["transforms"])
    return Person(
        subject=subject.id, vertices=vertices, faces=faces, vertex_bones=bones, keypoints=p["keypoints"],
        joints=p["joints"], angles=p["angles"], bone_scales=p["bone_scales"], rest_joints=p["rest_joints"],
        transforms=p["transforms"], pose=p["pose"], global_orient=p["global_orient"], transl=p["transl"],
        bone=p["bone"], shape=p["shape"], hair=posed_hair, cloth=cloth, skirt=skirt,
    )  # fmt: skip


# ------------------------------------------------------------------------------------------------
# A worker's state


@dataclass
class Scene:
    """One image's world, everything its render and labels read, drawn before either from the
    sample's random stream (:meth:`SampleMaker.draw_scene`; a sequence makes one per frame).

    Attributes:
        index: the sample's index.
        people: the posed and placed people (mesh, texture and rig, hair, cloth; each with its
            ``outline``).
        camera: the image's :class:`blsm.camera.Camera`, which holds the image size (``width``,
            ``height``): the one place a scene says it.
        camera_info: what the camera draw records (view, truncation, lens).
        background: the environment that lights the people, and the backplate behind them.
        occluders: objects in front of or under the people (:class:`synth.occluders.Occluder`).
        extra: top-level label keys the scene adds (the occluders' records; a sequence's frame).
    """

    index: int
    people: list[Person]
    camera: Any
    camera_info: dict[str, Any]
    background: Background
    occluders: list[Any] = field(default_factory=list)
    extra: dict[str, Any] | None = None


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
        self.backdrop = background_kind(cfg.background.kind)
        self._backdrop_state = self.backdrop.open(cfg.background)  # its files and caches
        # Hair is grown on Anny's stand-in people only: user scans carry their own.
        self.hair = cfg.hair.enabled and cfg.pipeline != "raw" and cfg.subjects.source == "anny"
        # With the backdrop composited, the path tracer renders only the people's window
        # (synth.render.people_window, passed to the kernel as data: no compile per image).
        # False renders whole frames (tests and benchmarks compare).
        self.windowed = True
        self.head_bone = list(m.bone_names).index("head")
        self._rigs: dict[int, Rig] = {}
        self._renderers: dict[tuple, PeopleRenderer] = {}
        self.topology = None  # labels.topology: the people's vertices in a second topology (synth.topology)
        if cfg.labels.topology:
            from synth.topology import Topology

            self.topology = Topology(cfg.labels.topology, cfg.labels.topology_name, m)

    def rig(self, si: int) -> Rig:
        """Subject ``si``'s :class:`Rig` (made on first use)."""
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
        spec, hair = None, None
        if self.hair:
            from synth.hair import subject_hair, subject_hair_spec

            spec = subject_hair_spec(s, asdict(self.cfg.hair.styles), self.cfg.seed)
            hair = subject_hair(s, m, spec, pipe)
        gspec, garments = None, None
        if self.cfg.garments.enabled:
            from synth.garments import subject_garment_spec, subject_garments

            g = self.cfg.garments
            gspec = subject_garment_spec(s, self.cfg.seed, asdict(g.fits), g.jacket, g.dress)
            garments = subject_garments(s, m, gspec)
        rig = Rig(mesh=RenderMesh.build(faces, uv, fuv), faces=faces,
                  texture=srgb_to_linear(tex.astype(np.float32) / 255.0), face_bones=lab.face_bones(faces, weights),
                  parents=parents, hair_spec=spec, hair=hair, garment_spec=gspec, garments=garments,
                  weights=weights if garments is not None else None)  # fmt: skip
        self._rigs[si] = rig
        return rig

    def background(self, rng: np.random.Generator, camera: Any) -> Background:
        """The image's background: the exposure and rotation, then the kind's own draws."""
        b = self.cfg.background
        scale = float(2.0 ** rng.uniform(*b.exposure_ev))
        rot = float(rng.uniform(0, 2 * math.pi))
        return self.backdrop.draw(self._backdrop_state, b, rng, camera, (camera.width, camera.height), rot, scale)

    def renderer(self, meshes: list[RenderMesh], textures: list[np.ndarray], backplate: bool,
                 size: tuple[int, int]) -> PeopleRenderer:
        """The scene for these people's meshes, ``size`` (width, height) pixels (the image's camera
        says it; a Mitsuba film's size is fixed when its scene is built). People of one topology and texture size (every
        Anny subject; the blsm pipeline always) share one scene of ``people.max`` slots, the
        unused ones hidden, so a worker compiles its kernels once for any people count; people of
        several topologies (scans, raw pipeline) get a scene per combination."""
        slots, shapes = meshes, [t.shape[:2] for t in textures]
        if len({m.key for m in meshes}) == 1 and len(set(shapes)) == 1:
            slots, shapes = [meshes[0]] * self.cfg.people.max, [shapes[0]] * self.cfg.people.max
        key = (tuple(m.key for m in slots), tuple(shapes), backplate, size)
        r = self._renderers.get(key)
        if r is None:
            if len(self._renderers) >= 4:
                self._renderers.pop(next(iter(self._renderers)))
            b = self.cfg.background
            r = PeopleRenderer(
                slots, shapes, *size,
                env_shape=(b.env_width // 2, b.env_width), variant=self.variant,
                max_depth=self.cfg.render.max_depth, backplate=backplate,
                denoise=self.cfg.render.denoise, denoise_threads=self.threads, hair=self.hair,
                sampler=self.cfg.render.sampler, denoise_quality=self.cfg.render.denoise_quality,
                garments=self.cfg.garments.enabled,
                occluders=self.cfg.occluder_slots,
            )  # fmt: skip
            self._renderers[key] = r
        return r

    def make(self, index: int, rng: np.random.Generator) -> dict[str, bytes]:
        """Sample ``index``'s fields, from ``rng`` (:func:`synth.dataset.shards.sample_rng`) alone:
        the scene drawn, rendered and labelled, then encoded."""
        scene = self.draw_scene(index, rng)
        frame, labels = self.render_frame(scene, rng)
        return self.encode(scene, frame, labels)

    def draw_scene(self, index: int, rng: np.random.Generator) -> Scene:
        """Sample ``index``'s :class:`Scene`: its people drawn, posed and placed, the camera, the
        background and the occluders, in that order of draws from ``rng``."""
        cfg = self.cfg
        n = int(rng.integers(cfg.people.min, cfg.people.max + 1))
        people: list[Person] = []
        close: dict[str, Any] | None = None
        if cfg.people.placement == "close":  # within reach, touching (synth.close); seats made there
            from synth.close import place_close

            people, occluders, close = place_close(self, n, rng)
        else:
            for _ in range(n):
                people.append(self.draw_person(rng, [p.si for p in people]))
            for p in people:
                v = p.shell()
                p.outline = v[outline_index(v)]
            for p, d in zip(people, place_people([footprint(p.outline) for p in people], cfg.people.gap, rng)):
                p.move(d - np.array([0.0, p.vertices[:, 1].min(), 0.0]))  # the body's feet on the floor y = 0
        outline = np.concatenate([p.outline for p in people])  # every person's hull vertices
        facing = facing_yaw_deg(people[0].global_orient) if cfg.camera.frontal_rate else 0.0
        camera, cam_info = sample_camera(outline, cfg.camera, rng, facing_deg=facing)
        back = self.background(rng, camera)
        if close is None:
            occluders = seats(people, self.model.bone_names, rng) if cfg.poses.seated_rate else []
        if cfg.occluders.enabled:
            from synth.occluders import place_occluders

            o = cfg.occluders
            occluders += place_occluders([footprint(p.outline) for p in people], camera, o.prob, o.max, cfg.people.gap, rng)
        extra = {"occluders": [q.to_json() for q in occluders]} if cfg.occluder_slots else None
        if close is not None:
            extra = {**(extra or {}), "placement": close}
        return Scene(index, people, camera, cam_info, back, occluders, extra)

    def draw_person(self, rng: np.random.Generator, taken: Sequence[int] = (), seated: bool = False,
                    yaw_deg: float | None = None) -> Person:
        """A subject drawn (:func:`draw_subject`, the image's people so far having subjects ``taken``)
        and posed by the pose source (at the origin, before placement); ``seated`` seats a prior
        pose, ``yaw_deg`` turns the body to face that way (:mod:`synth.close`)."""
        si = draw_subject(rng, len(self.subjects), taken, self.cfg.people.distinct)
        s = self.subjects[si]
        age = s.meta.get("phenotype", {}).get("age_years")
        x, orient, motion = self.poses.sample(rng, child=age is not None and age < 18.0, seated=seated)
        if yaw_deg is not None:
            from synth.close import turn_to

            orient = turn_to(orient, yaw_deg)
        p = self.pose(si, x, orient, np.zeros(3, np.float32))
        p.motion = motion
        return p

    def pose(self, si: int, x: np.ndarray, orient: np.ndarray, transl: np.ndarray) -> Person:
        """Subject ``si`` posed by :func:`pose_person` with its rig's subdivision and hair; ``si``
        and ``rig`` attached."""
        rig = self.rig(si)
        subdivision = None if rig.parents is None else (rig.parents, rig.faces)
        garments = None if rig.garments is None else (rig.garments, rig.weights)
        p = pose_person(self.subjects[si], self.model, self.cfg.pipeline, x, orient, transl, subdivision, rig.hair,
                        garments)  # fmt: skip
        p.si, p.rig = si, rig
        return p

    def render_frame(self, scene: Scene, rng: np.random.Generator) -> tuple[Any, dict[str, Any]]:
        """:meth:`render` and :meth:`labels` of ``scene``."""
        frame = self.render(scene, rng)
        return frame, self.labels(scene, frame)

    def render(self, scene: Scene, rng: np.random.Generator) -> Any:
        """Path-trace ``scene``: its placed people and the occluders in front of them, over its
        background; ``rng`` draws the render's seed (and the backdrop's lens effects)."""
        cfg = self.cfg
        people, camera, cam_info, back = scene.people, scene.camera, scene.camera_info, scene.background
        occ = _occluder_meshes(scene.occluders)
        outline = np.concatenate([p.outline for p in people] + [v.astype(np.float32) for _, v, _, _ in occ])
        rigs = [p.rig for p in people]
        # With the shadow catcher or a thin lens the environment is hidden from the camera (as behind
        # a backplate) and the backdrop is composited after the render: darkened by the people's
        # shadows, blurred by the lens.
        composite = cfg.ground.shadows or "f_number" in cam_info
        r = self.renderer([q.mesh for q in rigs], [q.texture for q in rigs], back.backplate is not None or composite,
                          (camera.width, camera.height))
        seed = int(rng.integers(2**31))
        frame = r.render(
            [p.vertices for p in people], [q.texture for q in rigs], camera,
            back.env, back.rotation, back.scale, None if composite else back.backplate, cfg.render.spp, seed,
            [(p.hair, q.hair.colours) for p, q in zip(people, rigs)] if self.hair else None,
            # Composited, the backdrop is not path traced: only the people's window is.
            people_window(camera, outline) if composite and self.windowed else None,
            [(p.cloth, p.skirt, None if p.skirt is None else q.garments.skirt_colours) for p, q in zip(people, rigs)]
            if self.cfg.garments.enabled else None,
            [(k, v, c) for k, v, _, c in occ],
        )  # fmt: skip
        if composite:
            self._composite_backdrop(r, frame, camera, cam_info, back, outline, rng)
        return frame

    def labels(self, scene: Scene, frame: Any) -> dict[str, Any]:
        """The labels of ``scene`` as ``frame`` rendered it (per pixel: who, which part and bone,
        depth, the surface point; per person: keypoints, boxes, visibility)."""
        people = scene.people
        occ = _occluder_meshes(scene.occluders)
        labels = lab.person_labels(
            frame, scene.camera,
            [{"vertices": p.vertices, "outline": p.outline, "faces": p.rig.faces, "face_bones": p.rig.face_bones,
              "keypoints": p.keypoints, **self._hair_labels(p), **_cloth_labels(p)} for p in people],
            self.bone_to_part, self.regions, self.is_joint, [(v, f) for _, v, f, _ in occ],
        )  # fmt: skip
        if labels["unassigned"]:
            raise RuntimeError(f"sample {scene.index}: {labels['unassigned']} hit pixels belong to no person's face")
        if self.cfg.labels.contact_distance or self.cfg.labels.occupancy:
            from synth.contacts import body_labels

            labels.update(body_labels(self.cfg, scene, self.bone_to_part, list(self.model.part_names)))
        return labels

    def _hair_labels(self, p: Person) -> dict[str, Any]:
        if p.hair is None:
            return {}
        from synth.hair import hair_faces

        return {"hair_vertices": p.hair, "hair_faces": hair_faces(), "hair_bone": self.head_bone}

    def _composite_backdrop(self, r: PeopleRenderer, frame: Any, camera: Any, cam_info: dict, back: Background,
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

    def encode(self, scene: Scene, frame: Any, labels: dict[str, Any],
               extra_people: list[dict[str, Any]] | None = None) -> dict[str, bytes]:
        """The sample's fields through the dataset format (:mod:`synth.dataset.format`): the image,
        the labels and the scene's record; ``scene.extra`` adds top-level label keys and
        ``extra_people`` keys per person (a sequence's, :mod:`synth.sequence`)."""
        m = self.model
        index, camera, cam_info, back, people = scene.index, scene.camera, scene.camera_info, scene.background, scene.people
        extra = scene.extra
        plist = [
            {**self._person_doc(p, lp), **(extra_people[i] if extra_people else {})}
            for i, (p, lp) in enumerate(zip(people, labels["people"]))
        ]
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
        if "contacts" in labels:
            doc["contacts"] = labels["contacts"]
        rgb = np.round(linear_to_srgb(frame.rgb) * 255.0).astype(np.uint8)
        return {
            "rgb.png": fmt.encode_png(rgb),
            "json": fmt.encode_json(doc),
            "mask.png": fmt.encode_png(labels["mask"]),
            "parts.png": fmt.encode_png(labels["parts"], fmt.PART_PALETTE),
            "bones.png": fmt.encode_png(labels["bones"], fmt.BONE_PALETTE),
            "depth.exr": fmt.encode_exr(labels["depth"]),
            "corr.npy.gz": fmt.encode_npy_gz(labels["corr"]),
            **({} if self.topology is None else self._topology_member(people)),
            **({"occupancy.npy.gz": fmt.encode_npy_gz(labels["occupancy"])} if "occupancy" in labels else {}),
        }

    def _topology_member(self, people: list[Person]) -> dict[str, bytes]:
        """``vertices_<name>.npy.gz``: (P, V2, 3) the people's bodies in ``labels.topology`` (:mod:`synth.topology`)."""
        from synth.topology import member

        v = [self.topology.vertices(self.subjects[p.si].registration, p.pose, p.global_orient, p.transl) for p in people]
        return {member(self.topology.name): fmt.encode_npy_gz(np.stack(v))}

    def _person_doc(self, p: Person, lp: dict[str, Any]) -> dict[str, Any]:
        """Person ``p``'s entry of the sample's ``people`` (``lp``: its labels from the render)."""
        from blsm.joint_limits import unconstrained_from_angles

        m = self.model
        x = p.pose
        if x is None:  # raw: the scan's own angles
            x = unconstrained_from_angles(torch.as_tensor(p.angles)[None], m.dof_limits)[0].numpy()
        lengths = _bone_lengths(p.rest_joints, p.keypoints, m)
        return {
            "subject": p.subject,
            "pipeline": self.cfg.pipeline,
            "motion": p.motion,
            **({"hair": p.rig.hair_spec.to_json()} if p.hair is not None else {}),
            **({"garments": p.rig.garment_spec.to_json()} if p.cloth is not None else {}),
            "blsm": {
                "pose": _l(x), "angles": _l(p.angles), "bone": _l(p.bone), "shape": _l(p.shape),
                "global_orient": _l(p.global_orient), "transl": _l(p.transl),
            },
            "bone_lengths": _l(lengths),
            "keypoints_3d": _l(p.keypoints),
            "keypoints_3d_cam": _l(lp["keypoints_3d_cam"]),
            "keypoints_2d": _l(lp["keypoints_2d"]),
            "visible": [bool(v) for v in lp["visible"]],
            "in_frame": [bool(v) for v in lp["in_frame"]],
            "box": lp["box"],
            "box_full": None if lp["box_full"] is None else _l(lp["box_full"]),
            "pixels": lp["pixels"],
        }  # fmt: skip


def _occluder_meshes(occluders: list[Any]) -> list[tuple[str, np.ndarray, np.ndarray, np.ndarray]]:
    """``(kind, vertices, faces, colours)`` of each occluder (:func:`synth.occluders.occluder_mesh`)."""
    if not occluders:
        return []
    from synth.occluders import occluder_mesh

    return [(o.kind, *occluder_mesh(o)) for o in occluders]


def _cloth_labels(p: Person) -> dict[str, Any]:
    """Person ``p``'s clothes for :func:`synth.labels.person_labels` (nothing without garments)."""
    if p.cloth is None:
        return {}
    from synth.garments import skirt_faces

    g = p.rig.garments
    out: dict[str, Any] = {"cloth_vertices": p.cloth}
    if p.skirt is not None:
        out.update(skirt_vertices=p.skirt, skirt_faces=skirt_faces(), skirt_face_bones=g.skirt_face_bones)
    return out


def _l(a: Any) -> Any:
    """Array to nested lists of Python floats rounded to 1e-6 (stable JSON across runs; the
    precision the validator allows for is stated in :mod:`synth.dataset.format`)."""
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
