"""Mitsuba 3 rendering of textured people with exact per-pixel labels from the same scene.

One :class:`PeopleRenderer` holds one loaded scene: a mesh per person slot (textured, diffuse), an
environment map that lights the scene (and shows as the background, or is hidden when a backplate
is composited behind the people), and two sensors that always share one OpenCV camera:

- ``sensor`` renders the image with the path tracer, ``spp`` samples per pixel (with ``denoise``,
  nested in the AOV integrator for albedo and normal, and denoised by :mod:`synth.denoise`), over
  the whole image or only the people's window (:func:`trace_window`: the window is data of one
  kernel, so a new window compiles nothing);
- ``label_sensor`` renders the AOV integrator (``depth``, ``position``, ``prim_index``) with one sample at
  every pixel centre (a non-jittered stratified sampler and a box filter), so every label pixel is
  the first hit of the ray through ``(u + 0.5, v + 0.5)``.

Every frame only updates the scene through ``mi.traverse`` (vertex positions and normals, textures,
environment, camera) and ``update()``; the scene is rebuilt only when a mesh topology or the image
size changes. Meshes are split at UV seams for rendering (Mitsuba keeps one UV per vertex) while
face indices stay those of the person's mesh.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass
from typing import Any

import numpy as np

from blsm.camera import Camera
from blsm.mesh import face_incidence, vertex_normals
from blsm.mitsuba_util import env_rotation, load_mitsuba, perspective_sensor, resolve_variant, set_camera

# Where an unused person slot's vertices all go (:meth:`PeopleRenderer._hide`): under the ground
# y = 0 that every person stands on and every camera looks down on or across.
HIDDEN_POINT = (0.0, -10.0, 0.0)


@dataclass(frozen=True)
class RenderMesh:
    """A person's mesh prepared for Mitsuba: vertices split at UV seams.

    Attributes:
        faces: (F, 3) faces of the person's mesh (vertex indices).
        split_vertex: (S,) original vertex of every render vertex.
        split_faces: (F, 3) faces over the render vertices (same order as ``faces``).
        texcoords: (S, 2) Mitsuba UVs (v down: ``1 - v`` of the mesh's v-up UVs).
        incidence: (V, F) :func:`blsm.mesh.face_incidence`, for the per-frame vertex normals.
    """

    faces: np.ndarray
    split_vertex: np.ndarray
    split_faces: np.ndarray
    texcoords: np.ndarray
    incidence: Any

    @staticmethod
    def build(faces: np.ndarray, uv: np.ndarray, faces_uv: np.ndarray) -> RenderMesh:
        pairs = np.stack([faces.reshape(-1), faces_uv.reshape(-1)], axis=1)
        uniq, inverse = np.unique(pairs, axis=0, return_inverse=True)
        tc = uv[uniq[:, 1]].astype(np.float32)
        tc[:, 1] = 1.0 - tc[:, 1]
        faces = np.asarray(faces, dtype=np.int64)
        return RenderMesh(
            faces=faces,
            split_vertex=uniq[:, 0],
            split_faces=inverse.reshape(-1, 3).astype(np.uint32),
            texcoords=tc,
            incidence=face_incidence(faces, int(faces.max()) + 1),  # the vertices faces use
        )

    @property
    def key(self) -> tuple[int, int, int]:
        return (len(self.split_vertex), len(self.faces), hash(self.split_faces.tobytes()))


@functools.lru_cache(maxsize=None)
def _hair_bsdf(variant: str) -> Any:
    """The hair's BSDF, one object per process and variant for every hair of every renderer (the
    colour is each hair mesh's own attribute). Dr.Jit traces a BSDF call once for each BSDF alive
    in the process, so each renderer's and slot's own copy made every render trace the principled
    BSDF again (about 4 ms a copy here)."""
    mi = load_mitsuba(variant)
    colour = {"type": "mesh_attribute", "name": "vertex_color"}
    return mi.load_dict({"type": "twosided", "bsdf": {
        "type": "principled", "base_color": colour, "roughness": 0.45, "specular": 0.35}})  # fmt: skip


@functools.lru_cache(maxsize=None)
def _skirt_bsdf(variant: str) -> Any:
    """The skirts' and occluders' BSDF (:mod:`synth.garments`, :mod:`synth.occluders`), one per
    process and variant like the hair's: two-sided diffuse (a skirt's inside shows under the hem),
    colour per vertex."""
    mi = load_mitsuba(variant)
    return mi.load_dict({"type": "twosided", "bsdf": {
        "type": "diffuse", "reflectance": {"type": "mesh_attribute", "name": "vertex_color"}}})  # fmt: skip


def people_window(camera: Camera, points: np.ndarray, quantum: int = 1, margin: int = 1) -> tuple[int, int, int, int]:
    """The pixels ``(x0, y0, width, height)`` that can see a person: the box of the projected
    ``points`` (the people's vertices or their hull vertices, ``synth.camera.outline_index``,
    hair included), ``margin`` pixels wider, its sides rounded up to a multiple of ``quantum``
    pixels, inside the image; the whole image when a point is not in front of the camera.
    (:func:`trace_window` takes the window as data, so its size costs no compile: no rounding
    is needed.)

    Pixel ``i`` spans ``[i, i + 1)`` (centres at ``i + 0.5``) and the film's box filter keeps a
    sample in its pixel, so a sample outside the window cannot see a person: the projection of a
    mesh lies in the box of its hull vertices' projections when they are all in front.
    """
    w, h = camera.width, camera.height
    pts = np.asarray(points, np.float64).reshape(-1, 3)
    if len(pts) == 0 or not (camera.world_to_camera(pts)[:, 2] > 0.01).all():  # 0.01: the near clip
        return 0, 0, w, h
    uv = camera.project(pts)
    lo = np.floor(uv.min(0)).astype(np.int64) - margin
    hi = np.floor(uv.max(0)).astype(np.int64) + 1 + margin
    out = []
    for a, b, n in ((lo[0], hi[0], w), (lo[1], hi[1], h)):
        a, b = max(int(a), 0), min(int(b), n)
        if b <= a:  # nobody in view: the smallest window
            a, b = 0, 1
        size = min(n, -(-(b - a) // quantum) * quantum)
        start = min(max(a - (size - (b - a)) // 2, 0), n - size)
        out.append((start, size))
    (x0, ww), (y0, wh) = out
    return x0, y0, ww, wh


def trace_window(
    mi: Any, scene: Any, sensor: Any, integrator: Any, window: tuple[int, int, int, int], spp: int, seed: int
) -> np.ndarray:
    """Path-trace the pixels of ``window`` ``(x0, y0, width, height)`` of ``sensor``'s film with
    ``integrator``: (height, width, C) float32, the film's channels (R, G, B, A, then the
    integrator's AOVs) averaged over ``spp`` samples a pixel.

    This is ``SamplingIntegrator::render`` (Mitsuba 3.9, ``src/render/integrator.cpp``) for a box
    filter and an uncropped film, with the window's offset and size, the samples per pixel's
    divisor and the seed entering the kernel as opaque values instead of literals: Mitsuba bakes a
    film crop's offset and size into the path tracer's kernel, so each new window compiled a new
    one (0.4 s on a CPU, 0.7 s on a GPU, per image). Sample ``k`` of wavefront index ``i`` goes to
    pixel ``i // spp`` of the window in row-major order and is seeded as ``mi.render`` seeds it, so
    over the whole image the samples are those of ``mi.render`` with the same seed. A sample stays in
    its pixel (box filter), so a pixel's value is the plain mean of its samples; no ray leaves the
    window.
    """
    import drjit as dr

    film = sensor.film()
    width, height = (int(v) for v in film.size())
    if tuple(int(v) for v in film.crop_size()) != (width, height) or any(int(v) for v in film.crop_offset()):
        raise ValueError("trace_window needs an uncropped film")
    x0, y0, ww, wh = (int(v) for v in window)
    sampler = sensor.sampler()
    sampler.set_sample_count(spp)
    spp = int(sampler.sample_count())
    n = ww * wh * spp
    sampler.set_samples_per_wavefront(spp)
    sampler.seed(dr.opaque(mi.UInt32, seed % 2**32), n)
    pixel = dr.arange(mi.UInt32, n) // dr.opaque(mi.UInt32, spp)
    cols = dr.opaque(mi.UInt32, ww)
    row = pixel // cols
    col = pixel - row * cols
    pos = mi.Point2f(mi.Float(col + dr.opaque(mi.UInt32, x0)), mi.Float(row + dr.opaque(mi.UInt32, y0)))
    sample_pos = pos + sampler.next_2d()
    time = mi.Float(sensor.shutter_open())
    if sensor.shutter_open_time() > 0.0:
        time += sampler.next_1d() * sensor.shutter_open_time()
    aperture = sampler.next_2d() if sensor.needs_aperture_sample() else mi.Point2f(0.5)
    ray, weight = sensor.sample_ray_differential(
        time, mi.Float(0.0), sample_pos * mi.ScalarVector2f(1.0 / width, 1.0 / height), aperture
    )
    if ray.has_differentials:
        ray.scale_differential(spp**-0.5)
    spec, valid, aovs = integrator.sample(scene, sampler, ray, None, mi.Bool(True))  # no participating media here
    rgb = weight * spec
    channels = [rgb.x, rgb.y, rgb.z]
    if mi.has_flag(film.flags(), mi.FilmFlags.Alpha):
        channels.append(dr.select(valid, 1.0, 0.0))
    # The AOV integrator repeats its nested integrator's R, G, B, A as the AOVs "image.*"; the film's
    # output leaves those out (they are its base channels), and so does this.
    channels += [a for name, a in zip(integrator.aov_names(), aovs) if not name.startswith("image.")]
    dr.eval(channels)  # one path-tracing kernel for every channel, then a sum per pixel of each
    sums = [dr.block_sum(c, spp) for c in channels]
    dr.eval(sums)
    out = np.stack([np.asarray(c) for c in sums], axis=-1).reshape(wh, ww, len(sums))
    return out * np.float32(1.0 / spp)


@dataclass
class Frame:
    """What one render returns.

    Attributes:
        rgb: (H, W, 3) float32 linear RGB (background included).
        alpha: (H, W) float32 coverage of the people in the RGB render.
        hit: (H, W) bool, a person is hit by the pixel-centre ray.
        position: (H, W, 3) float32 world position of the hit.
        face: (H, W) int64 face index of the hit (-1 where no hit).
    """

    rgb: np.ndarray
    alpha: np.ndarray
    hit: np.ndarray
    position: np.ndarray
    face: np.ndarray


class PeopleRenderer:
    """A Mitsuba scene for a fixed list of person meshes (topologies) and an image size."""

    def __init__(
        self,
        meshes: list[RenderMesh],
        texture_shapes: list[tuple[int, int]],
        width: int,
        height: int,
        env_shape: tuple[int, int] = (256, 512),
        variant: str | None = None,
        max_depth: int = 4,
        backplate: bool = False,
        instanced: bool = True,
        denoise: bool = False,
        denoise_threads: int = 1,
        hair: bool = False,
        sampler: str = "independent",
        denoise_quality: str = "high",
        garments: bool = False,
        occluders: int = 0,
    ) -> None:
        """Load the scene.

        Args:
            instanced: each person mesh in a shape group seen through an instance (the default;
                see below); False puts the meshes directly in the scene (benchmarks compare both).
            denoise: render albedo and normal with the image's own samples and denoise the image
                with Open Image Denoise (:mod:`synth.denoise`); labels are not affected.
            denoise_threads: CPU threads of the denoiser.
            denoise_quality: OIDN's ``high``, ``balanced`` or ``fast`` filter.
            hair: every person slot also holds a hair (:mod:`synth.hair`; the same topology for all):
                ribbons with per-vertex colour, seen from both sides, slightly glossy (a two-sided
                principled BSDF, roughness 0.45, specular 0.35).
            garments: every person slot also holds a cloth layer (the person's topology, texture
                and BSDF: one BSDF object for both) and a skirt (:mod:`synth.garments`; the same
                topology for all; hidden where a person has none).
            occluders: slots for objects in front of the people (:mod:`synth.occluders`), each a
                box and a cylinder mesh (one shown, or none), colour per vertex.
            sampler: the path tracer's Mitsuba sampler (``independent``, or a stratified,
                multi-jittered or low-discrepancy one: less noise at the same samples per pixel).
        """
        self.variant = resolve_variant(variant)
        self.instanced = instanced
        self.mi = load_mitsuba(self.variant)
        self.width, self.height = width, height
        self.meshes = meshes
        self.backplate = backplate
        self.hair = hair
        self.garments = garments
        self.occluders = occluders
        self.denoiser = None
        if denoise:
            from synth.denoise import shared_denoiser

            self.denoiser = shared_denoiser(denoise_threads, denoise_quality)
        scene = self._scene_dict(env_shape, max_depth, sampler)
        for i, (m, tshape) in enumerate(zip(meshes, texture_shapes)):
            shapes = self._person_shapes(i, m, tshape)
            # Each person is a shape group seen through one identity instance. Embree then gives
            # the person its own BVH, which the group rebuilds after each vertex update at Embree's
            # default quality instead of the scene's RTC_BUILD_QUALITY_HIGH. `make bench` measured
            # the per-image scene update at 16 ms instead of 29 ms (2 threads; 14 against 44-48 ms
            # on one) for a render about 10 % slower. Labels are the same; the image differs in a
            # few pixels where a light path took another turn (Monte Carlo noise;
            # tests/synth/test_people_renderer.py).
            if instanced:
                scene[f"group_{i}"] = {"type": "shapegroup", **shapes}
                scene[f"instance_{i}"] = {"type": "instance", "shapegroup": {"type": "ref", "id": f"group_{i}"}}
            else:
                scene.update(shapes)
        for k in range(occluders):
            from synth.occluders import KINDS, occluder_faces, occluder_vertex_count

            for kind in KINDS:
                scene[f"occl_{kind}_{k}"] = self._coloured_mesh(f"occl_{kind}_{k}", occluder_vertex_count(kind),
                                                                occluder_faces(kind), _skirt_bsdf(self.variant))  # fmt: skip
        mi = self.mi
        self.scene = mi.load_dict(scene)
        self.params = mi.traverse(self.scene)
        self.environment = self.scene.environment()  # the envmap (synth.ground.emitter_backdrop)
        self.label_integrator = mi.load_dict({"type": "aov", "aovs": "dd:depth,pos:position,pi:prim_index"})
        # A second, unused emitter instance. With a single emitter alive in the process, Dr.Jit
        # devirtualises the emitter calls and inlines the environment map into the path tracer's
        # kernel at every call site, which made that kernel 20-25 % slower here (measured on
        # LLVM, 2026-11-24; the rendered image is bit-identical either way). `make bench`
        # reports the bare render with and without it.
        self.spare_emitter = mi.load_dict({"type": "constant"})
        self._warm = False
        self._hair_inc = None
        self._skirt_inc = None
        self._hidden: set[int] = set()  # slots collapsed out of sight (:meth:`_hide`)
        self._textures: dict[int, np.ndarray] = {}  # the texture array each slot shows now
        self._env: np.ndarray | None = None  # the environment array uploaded now

    def _scene_dict(self, env_shape: tuple[int, int], max_depth: int, sampler: str) -> dict[str, Any]:
        """The scene without its people: the integrator, the two sensors and the environment."""
        path = {"type": "path", "max_depth": max_depth, "hide_emitters": self.backplate}
        if self.denoiser is not None:
            # The path tracer nested in the AOV integrator: colour, albedo and normal of the same
            # samples (film channels R, G, B, A, albedo RGB, normal XYZ).
            path = {"type": "aov", "aovs": "alb:albedo,nn:sh_normal", "image": path}
        w, h = self.width, self.height
        return {
            "type": "scene",
            "integrator": path,
            "sensor": perspective_sensor(w, h, {"type": sampler, "sample_count": 16}, "rgba"),
            # One sample at every pixel centre: a non-jittered stratified sampler.
            "label_sensor": perspective_sensor(w, h, {"type": "stratified", "sample_count": 1, "jitter": False}, "rgb"),
            "env": {
                "type": "envmap",
                "bitmap": self.mi.Bitmap(np.full((*env_shape, 3), 0.5, dtype=np.float32)),
            },
        }

    def _person_shapes(self, i: int, m: RenderMesh, tshape: tuple[int, int]) -> dict[str, Any]:
        """Slot ``i``'s shapes: the person's mesh (diffuse, textured; placeholder vertices and
        texels until :meth:`render`) and, with hair, the hair's."""
        mi = self.mi
        props = mi.Properties()
        bsdf = props["bsdf"] = mi.load_dict(
            {
                "type": "diffuse",
                "reflectance": {
                    "type": "bitmap",
                    "bitmap": mi.Bitmap(np.full((*tshape, 3), 0.5, dtype=np.float32)),
                    "raw": True,
                    "filter_type": "bilinear",
                },
            }
        )
        shapes = {f"person_{i}": self._textured_mesh(f"person_{i}", m, bsdf)}
        if self.hair:
            shapes[f"hair_{i}"] = self._hair_mesh(i)
        if self.garments:  # after the person: the shared BSDF's parameters are the person's
            from synth.garments import skirt_faces, skirt_vertex_count

            shapes[f"cloth_{i}"] = self._textured_mesh(f"cloth_{i}", m, bsdf)
            shapes[f"skirt_{i}"] = self._coloured_mesh(f"skirt_{i}", skirt_vertex_count(), skirt_faces(),
                                                       _skirt_bsdf(self.variant))  # fmt: skip
        return shapes

    def _textured_mesh(self, name: str, m: RenderMesh, bsdf: Any) -> Any:
        mi = self.mi
        props = mi.Properties()
        props["bsdf"] = bsdf
        mesh = mi.Mesh(name, len(m.split_vertex), len(m.split_faces), props=props, has_vertex_normals=True,
                       has_vertex_texcoords=True)  # fmt: skip
        p = mi.traverse(mesh)
        p["vertex_positions"] = mi.Float(np.zeros(3 * len(m.split_vertex), dtype=np.float32))
        p["faces"] = mi.UInt32(m.split_faces.reshape(-1))
        p["vertex_texcoords"] = mi.Float(m.texcoords.reshape(-1))
        p.update()
        return mesh

    def _coloured_mesh(self, name: str, nv: int, faces: np.ndarray, bsdf: Any) -> Any:
        """A mesh of ``nv`` vertices and ``faces`` with a per-vertex colour (``vertex_color``)."""
        mi = self.mi
        props = mi.Properties()
        props["bsdf"] = bsdf
        mesh = mi.Mesh(name, nv, len(faces), props=props, has_vertex_normals=True)
        mesh.add_attribute("vertex_color", 3, mi.Float(np.full(3 * nv, 0.1, np.float32)))
        p = mi.traverse(mesh)
        p["vertex_positions"] = mi.Float(np.zeros(3 * nv, dtype=np.float32))
        p["faces"] = mi.UInt32(faces.reshape(-1).astype(np.uint32))
        p.update()
        return mesh

    def _hide(self, i: int) -> None:
        """Collapse slot ``i``'s meshes (person, hair, clothes) to one point under the ground:
        zero-area triangles, which no ray hits (no camera, shadow ray or label ray sees them).
        Uploaded once until the slot shows a person again."""
        if i in self._hidden:
            return
        names = [f"person_{i}"] + ([f"hair_{i}"] if self.hair else [])
        names += [f"cloth_{i}", f"skirt_{i}"] if self.garments else []
        for name in names:
            self._collapse(i, name)
        self._hidden.add(i)

    def _collapse(self, i: int | None, name: str) -> None:
        """Collapse mesh ``name`` (of person slot ``i``, or of the scene itself with None)."""
        mi, p = self.mi, self.params
        key = f"group_{i}.{name}" if self.instanced and i is not None else name
        nv = len(p[f"{key}.vertex_positions"]) // 3
        p[f"{key}.vertex_positions"] = mi.Float(np.tile(np.array(HIDDEN_POINT, np.float32), nv))
        p[f"{key}.vertex_normals"] = mi.Float(np.tile(np.array([0.0, 1.0, 0.0], np.float32), nv))

    def _hair_mesh(self, i: int) -> Any:
        from synth.hair import hair_faces, num_vertices

        return self._coloured_mesh(f"hair_{i}", num_vertices(), hair_faces(), _hair_bsdf(self.variant))

    def _assign_clothes(self, i: int, layer: np.ndarray, skirt: np.ndarray | None, colours: np.ndarray | None) -> None:
        mi, p = self.mi, self.params
        m = self.meshes[i]
        key = f"group_{i}.cloth_{i}" if self.instanced else f"cloth_{i}"
        normals = vertex_normals(np.asarray(layer, np.float32), m.faces, m.incidence)
        p[f"{key}.vertex_positions"] = mi.Float(np.ascontiguousarray(layer[m.split_vertex], dtype=np.float32).reshape(-1))
        p[f"{key}.vertex_normals"] = mi.Float(np.ascontiguousarray(normals[m.split_vertex]).reshape(-1))
        if skirt is None:
            self._collapse(i, f"skirt_{i}")
            return
        from synth.garments import skirt_faces, skirt_vertex_count

        if self._skirt_inc is None:
            self._skirt_inc = face_incidence(skirt_faces(), skirt_vertex_count())
        key = f"group_{i}.skirt_{i}" if self.instanced else f"skirt_{i}"
        normals = vertex_normals(np.asarray(skirt, np.float32), skirt_faces(), self._skirt_inc)
        p[f"{key}.vertex_positions"] = mi.Float(np.ascontiguousarray(skirt, dtype=np.float32).reshape(-1))
        p[f"{key}.vertex_normals"] = mi.Float(np.ascontiguousarray(normals).reshape(-1))
        p[f"{key}.vertex_color"] = mi.Float(np.ascontiguousarray(colours, dtype=np.float32).reshape(-1))

    def _assign_occluders(self, occluders) -> None:
        from synth.occluders import KINDS, occluder_faces

        mi, p = self.mi, self.params
        for k in range(self.occluders):
            shown = occluders[k][0] if k < len(occluders) else None
            for kind in KINDS:
                if kind != shown:
                    self._collapse(None, f"occl_{kind}_{k}")
                    continue
                _, v, colours = occluders[k]
                normals = vertex_normals(np.asarray(v, np.float32), occluder_faces(kind).astype(np.int64))
                p[f"occl_{kind}_{k}.vertex_positions"] = mi.Float(np.ascontiguousarray(v, dtype=np.float32).reshape(-1))
                p[f"occl_{kind}_{k}.vertex_normals"] = mi.Float(np.ascontiguousarray(normals, dtype=np.float32).reshape(-1))
                p[f"occl_{kind}_{k}.vertex_color"] = mi.Float(np.ascontiguousarray(colours, dtype=np.float32).reshape(-1))
        if self.occluders:
            p.update()

    def _hair_incidence(self) -> Any:
        if self._hair_inc is None:
            from synth.hair import hair_faces, num_vertices

            self._hair_inc = face_incidence(hair_faces(), num_vertices())
        return self._hair_inc

    def render(
        self,
        vertices: list[np.ndarray],
        textures: list[np.ndarray],
        camera: Camera,
        env: np.ndarray,
        env_rotation: float,
        env_scale: float,
        backplate: np.ndarray | None = None,
        spp: int = 16,
        seed: int = 0,
        hair: list[tuple[np.ndarray, np.ndarray]] | None = None,
        window: tuple[int, int, int, int] | None = None,
        clothes: list[tuple[np.ndarray, np.ndarray | None, np.ndarray | None]] | None = None,
        occluders: list[tuple[str, np.ndarray, np.ndarray]] = (),
    ) -> Frame:
        """Render one frame.

        Args:
            vertices: per person, (V, 3) world positions of the person's mesh, one person per slot
                from the first; the renderer's other slots are hidden (:meth:`_hide`), so that one
                scene, and so one set of kernels, serves any number of people up to its slots.
            textures: per person, (H, W, 3) linear albedo float32 (row 0 = top of the image).
            camera: the OpenCV camera (its size must be the renderer's).
            env: (He, We, 3) linear RGB latitude-longitude environment (lights the scene).
            env_rotation: radians about +Y.
            env_scale: radiance scale (exposure).
            backplate: (H, W, 3) linear RGB drawn behind the people (the renderer must have been
                built with ``backplate=True``), or None to see the environment.
            spp: samples per pixel of the image.
            seed: the path tracer's seed.
            hair: per person, the posed hair's (H, 3) vertices and (H, 3) linear colours (the
                renderer must have been built with ``hair=True``); a hair hit is reported by its
                face index in the hair (``Frame.face``), which :func:`synth.labels.assign_hits`
                tells from the body's faces by the hit position.
            window: ``(x0, y0, width, height)`` pixels that hold every person (:func:`people_window`):
                the path tracer renders only these (:func:`trace_window`; the samples of a pixel
                are those of the full render's distribution, another random stream), and the
                image is 0 with alpha 0 elsewhere. Only where the environment is hidden
                (``backplate=True``), since outside the window nothing would show it. The label
                pass always covers the whole image.
            clothes: per person, the posed cloth layer's (V, 3) vertices (the person's topology)
                and the posed skirt's (S, 3) vertices and (S, 3) linear colours, or None, None
                without a skirt (the renderer must have been built with ``garments=True``).
            occluders: per object, its kind, (V, 3) world vertices and (V, 3) linear colours
                (:func:`synth.occluders.occluder_mesh`), at most the renderer's ``occluders``
                slots. A hit on an occluder is reported by its face index like any other.
        """
        mi = self.mi
        if (camera.width, camera.height) != (self.width, self.height):
            raise ValueError(f"camera is {camera.width}x{camera.height}, renderer {self.width}x{self.height}")
        n = len(vertices)
        if not 1 <= n <= len(self.meshes) or len(textures) != n:
            raise ValueError(f"need 1 to {len(self.meshes)} meshes and as many textures, got {n}, {len(textures)}")
        if (hair is not None) != self.hair or (hair is not None and len(hair) != n):
            raise ValueError(f"this renderer {'needs' if self.hair else 'has no'} a hair per person")
        if (clothes is not None) != self.garments or (clothes is not None and len(clothes) != n):
            raise ValueError(f"this renderer {'needs' if self.garments else 'has no'} clothes per person")
        if len(occluders) > self.occluders:
            raise ValueError(f"this renderer has {self.occluders} occluder slots, got {len(occluders)} occluders")
        full = (0, 0, self.width, self.height)
        window = full if window is None else tuple(int(w) for w in window)
        x0, y0, ww, wh = window
        if window != full and not self.backplate:
            raise ValueError("a render window needs the environment hidden: build the renderer with backplate=True")
        if not (0 <= x0 and 0 <= y0 and ww > 0 and wh > 0 and x0 + ww <= self.width and y0 + wh <= self.height):
            raise ValueError(f"render window {window} is not inside the {self.width}x{self.height} image")
        # The first update of a freshly loaded scene renders a few pixels differently from every
        # later update of the same values (observed; making every scene value opaque at load time
        # does not remove it), so the first frame assigns twice. A trace of the previous image
        # remains even so: rarely one pixel of the RGB differs by about 3e-4 depending on which
        # sample the scene rendered before (the label pass never differed). Labels are therefore
        # a function of (seed, index); the RGB is, up to such a pixel.
        for _ in range(1 if self._warm else 2):
            if not self._warm:
                self._textures.clear()  # both warm-up assignments upload everything
                self._env = None
            self._assign(vertices, textures, camera, env, env_rotation, env_scale, hair, clothes)
            self._assign_occluders(occluders)
        self._warm = True
        sensors = self.scene.sensors()
        image = trace_window(mi, self.scene, sensors[0], self.scene.integrator(), window, spp, seed)
        aov = np.asarray(
            mi.TensorXf(mi.render(self.scene, sensor=sensors[1], integrator=self.label_integrator, spp=1))
        )
        if self.denoiser is not None:
            from synth.denoise import denoise_inputs

            color, alpha, albedo, normal = denoise_inputs(image)
            rgb = self.denoiser(color, albedo, normal)
        else:
            rgb, alpha = image[..., :3], np.clip(image[..., 3], 0.0, 1.0)
        if window != full:  # the window's pixels into the whole image (no person outside: RGB and alpha 0)
            rgb_w, alpha_w = rgb, alpha
            rgb = np.zeros((self.height, self.width, 3), np.float32)
            alpha = np.zeros((self.height, self.width), np.float32)
            rgb[y0 : y0 + wh, x0 : x0 + ww], alpha[y0 : y0 + wh, x0 : x0 + ww] = rgb_w, alpha_w
        if backplate is not None:
            if not self.backplate:
                raise ValueError("this renderer shows the environment; build it with backplate=True")
            rgb = rgb + (1.0 - alpha[..., None]) * backplate  # film RGB is alpha-weighted
        hit = aov[..., 0] > 0.0  # the ray distance; 0 where nothing is hit
        position = aov[..., 1:4]
        face = np.rint(aov[..., 4]).astype(np.int64)
        face[~hit] = -1
        return Frame(rgb=rgb.astype(np.float32), alpha=alpha, hit=hit, position=position, face=face)

    def _assign(self, vertices, textures, camera, env, env_rotation_rad, env_scale, hair=None, clothes=None) -> None:
        mi, p = self.mi, self.params
        import drjit as dr

        def opaque(x: float) -> Any:
            # A plain float would enter the compiled kernel as a literal: a new exposure or camera
            # would then recompile the path tracer (~0.4 s of LLVM per image) instead of reusing it.
            return dr.opaque(mi.Float, float(x))

        for i, (m, v, tex) in enumerate(zip(self.meshes, vertices, textures)):
            normals = vertex_normals(np.asarray(v, np.float32), m.faces, m.incidence)
            key = f"group_{i}.person_{i}" if self.instanced else f"person_{i}"
            self._hidden.discard(i)
            p[f"{key}.vertex_positions"] = mi.Float(np.ascontiguousarray(v[m.split_vertex]).reshape(-1))
            p[f"{key}.vertex_normals"] = mi.Float(np.ascontiguousarray(normals[m.split_vertex]).reshape(-1))
            if self._textures.get(i) is not tex:  # uploading 1024^2 texels costs ~3 ms
                p[f"{key}.bsdf.reflectance.data"] = mi.TensorXf(np.ascontiguousarray(tex, dtype=np.float32))
                self._textures[i] = tex
        for i in range(len(vertices), len(self.meshes)):
            self._hide(i)
        for i, (v, colours) in enumerate(hair or []):
            from synth.hair import hair_faces

            key = f"group_{i}.hair_{i}" if self.instanced else f"hair_{i}"
            normals = vertex_normals(np.asarray(v, np.float32), hair_faces(), self._hair_incidence())
            p[f"{key}.vertex_positions"] = mi.Float(np.ascontiguousarray(v, dtype=np.float32).reshape(-1))
            p[f"{key}.vertex_normals"] = mi.Float(np.ascontiguousarray(normals).reshape(-1))
            p[f"{key}.vertex_color"] = mi.Float(np.ascontiguousarray(colours, dtype=np.float32).reshape(-1))
        for i, (layer, skirt, colours) in enumerate(clothes or []):
            self._assign_clothes(i, layer, skirt, colours)
        if self._env is not env:  # the same HDRI again: its texels and sampling tables are kept
            p["env.data"] = mi.TensorXf(np.ascontiguousarray(env, dtype=np.float32))
            self._env = env
        p["env.scale"] = opaque(env_scale)
        rot = np.eye(4)
        rot[:3, :3] = env_rotation(env_rotation_rad)
        p["env.to_world"] = mi.AffineTransform4f(rot)
        for name in ("sensor", "label_sensor"):
            set_camera(mi, p, name, camera, opaque)
        p.update()
