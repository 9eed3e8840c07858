"""``synth validate``: check every sample of a dataset against its own geometry.

Per dataset (a folder without a readable manifest is bad input, a ``ValueError``): the manifest is
complete, every shard exists and its SHA-256 matches,
every subject file matches ``subjects/index.json``.

Per sample (the person's mesh is rebuilt from ``subjects/`` and the sample's BLSM parameters):

- all fields are present and decode, and their sizes agree with ``image``;
- ``keypoints_3d_cam = R keypoints_3d + t`` and ``keypoints_2d`` is their projection with ``K``
  for keypoints in front of the camera, up to what the JSON's 6-decimal rounding of ``K``, ``R``,
  ``t`` and the keypoints allows (per keypoint, :func:`synth.dataset.format.projection_tolerance`: under
  1e-3 px for a person filling the image, however long the lens); the rebuilt keypoints equal the
  stored ones;
- visible keypoints are in frame and lie inside their person's mask;
- ``box`` is the bounding box of the person's mask and holds its visible keypoints;
- the mask matches the projected mesh: the union of the people's projected triangles (less the
  pixels an occluder of the sample's ``occluders`` covers, :mod:`synth.occluders`, where a person
  may be hidden), tested at
  pixel centres, equals the foreground mask up to ``EDGE_PIXELS`` pixels on triangle edges;
- every mask pixel's correspondence (face, barycentric) on the rebuilt mesh (the body, then its hair
  rebuilt from the sample's ``hair`` spec, :mod:`synth.hair`, then its clothes rebuilt from the
  ``garments`` spec, :mod:`synth.garments`: the cloth layer and the skirt) projects to the pixel's centre, up to
  what the labels' single precision, the rebuild from rounded parameters and the rounding of ``K``,
  ``R``, ``t`` allow (per pixel, :func:`synth.dataset.format.correspondence_tolerance`: 1.4e-3 px for a
  surface facing a 600 mm lens 60 m away in a 128 px image, more where the surface is seen edge-on),
  at the stored depth (``DEPTH_M``) (:func:`check_correspondences`); parts and bones agree with the
  mask;
- ``vertices_<name>`` (with ``labels.topology``): each person's body rebuilt by the reparameterised
  model from the stored parameters (:func:`check_topology`, within ``TOPOLOGY_M``);
- clothes: the labels are the body's (keypoints rebuilt from the body alone), the mask is the
  projection of body, hair and clothes, and a pixel on the cloth layer has the bone of the body face
  under it (:func:`check_cloth_bones`).
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from blsm.camera import Camera
from blsm.io import sha256_file
from synth.dataset import format as fmt
from synth.dataset.shards import FORMAT as SHARDS_FORMAT
from synth.dataset.shards import MANIFEST, read_shard
from synth.raster import rasterise

DEPTH_M = 1e-4
TOPOLOGY_M = 1e-4  # a second topology's vertex rebuilt from the 6-decimal JSON parameters, as keypoints_3d
EDGE_PIXELS = 0.002  # fraction of the foreground area (at least 2 pixels)


@dataclass
class Report:
    samples: int = 0
    failures: list[str] = field(default_factory=list)

    def fail(self, where: str, msg: str) -> None:
        self.failures.append(f"{where}: {msg}")


def coverage(verts2d: np.ndarray, faces: np.ndarray, width: int, height: int) -> np.ndarray:
    """(H, W) bool: pixel centres inside any of the projected triangles (either winding)."""
    out = np.zeros(height * width, bool)
    # Pixel (u, v) has its centre at (u + 0.5, v + 0.5).
    out[rasterise(verts2d[faces] - 0.5, width, height)[0]] = True
    return out.reshape(height, width)


class MeshRebuilder:
    """Rebuilds a sample's posed meshes from ``subjects/`` and the stored parameters, posed as the
    generator posed them (:func:`synth.sample.pose_person`)."""

    def __init__(self, dataset: Path, config: dict[str, Any]) -> None:
        import blsm
        from synth.sample import subdivide

        self.model = blsm.load()
        self.subjects: dict[str, Any] = {}
        self.hair: dict[tuple, Any] = {}
        self.garments: dict[tuple, Any] = {}
        self.body_bones: dict[str, np.ndarray] = {}  # a clothed subject's face bones (rigged pipeline)
        self.cloth: tuple[int, np.ndarray] | None = None  # the last person's (first layer face, body face bones)
        self.dataset = dataset
        self.regions: dict[tuple, dict[str, np.ndarray]] = {}  # a sequence person's contact regions
        self.subdivide = bool(config.get("subdivide")) and config.get("pipeline") == "blsm"
        self.parents = subdivide(self.model.faces.numpy()) if self.subdivide else None
        labels = config.get("labels") or {}
        self.contact_distance = float(labels.get("contact_distance") or 0.0)  # synth.contacts
        self.occupancy = int(labels.get("occupancy") or 0)
        self.body_faces = np.zeros((0, 3), np.int64)  # the last person's body faces
        self.topology = None  # labels.topology (synth.topology): the people's vertices in a second topology
        if labels.get("topology"):
            from synth.topology import Topology

            self.topology = Topology(labels["topology"], labels.get("topology_name", "topo2"), self.model)

    def mesh(self, person: dict) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Sample person ``person``'s body and hair: (V, 3) float64 vertices, (F, 3) faces (the
        hair's after the body's) and (K, 3) keypoints; the body's vertex bones in ``self.bones``."""
        from synth.sample import pose_person
        from synth.subjects import load_subject

        sid = person["subject"]
        if sid not in self.subjects:
            self.subjects[sid] = load_subject(self.dataset / "subjects" / f"{sid}.npz")
        s = self.subjects[sid]
        b = person["blsm"]
        pipe = person["pipeline"]
        params = {k: np.asarray(b[k], np.float32) for k in ("pose", "global_orient", "transl")}
        hair = None
        if person.get("hair") is not None:  # the hair follows the body's faces (synth.labels)
            from synth.hair import HairSpec, subject_hair

            key = (sid, pipe, json.dumps(person["hair"], sort_keys=True))
            if key not in self.hair:
                self.hair[key] = subject_hair(s, self.model, HairSpec.from_json(person["hair"]), pipe)
            hair = self.hair[key]
        garments = None
        if person.get("garments") is not None:  # the clothes follow the hair's faces (synth.labels)
            from synth.garments import GarmentSpec, subject_garments

            key = (sid, json.dumps(person["garments"], sort_keys=True))
            if key not in self.garments:
                self.garments[key] = subject_garments(s, self.model, GarmentSpec.from_json(person["garments"]))
            garments = (self.garments[key], s.weights)
        p = pose_person(s, self.model, pipe, params["pose"], params["global_orient"], params["transl"],
                        self.parents, hair, garments)  # fmt: skip
        v, f, kp = p.vertices, p.faces, p.keypoints
        self.body_faces = p.faces
        self.bones = p.vertex_bones  # the body's, for a sequence's contact regions
        if pipe == "raw":  # the scan as captured, moved to its place in the image
            d = params["transl"] - s.registration["transl"]
            v, kp = v + d, kp + d
        self.last_body = (np.asarray(v, np.float64), p.faces)  # the body alone (contacts, occupancy)
        if p.hair is not None:
            from synth.hair import hair_faces

            f = np.concatenate([f, hair_faces() + len(v)])
            v = np.concatenate([v, p.hair])
        self.cloth = None
        if p.cloth is not None:
            from synth.garments import skirt_faces
            from synth.labels import face_bones

            if sid not in self.body_bones:  # per subject, not per person and sample
                self.body_bones[sid] = face_bones(p.faces, s.weights)
            self.cloth = (len(f), self.body_bones[sid])
            f, v = np.concatenate([f, p.faces + len(v)]), np.concatenate([v, p.cloth])
            if p.skirt is not None:
                f, v = np.concatenate([f, skirt_faces() + len(v)]), np.concatenate([v, p.skirt])
        return v.astype(np.float64), f, kp


def validate(dataset: str | Path, max_failures: int = 50, log: Any = None) -> Report:
    """Check a dataset folder; return a report (``failures`` empty when everything holds).

    Raises:
        ValueError: one line naming the file, when the folder holds no readable manifest of a
            dataset (bad input, not a failed validation).
    """
    dataset = Path(dataset)
    rep = Report()
    man_path = dataset / MANIFEST
    if not man_path.is_file():
        raise ValueError(f"{man_path}: no dataset manifest here")
    try:
        man = json.loads(man_path.read_bytes().decode("utf-8"))
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise ValueError(f"{man_path}: unreadable manifest ({exc})") from None
    if not isinstance(man, dict) or man.get("format") != SHARDS_FORMAT:
        raise ValueError(f"{man_path}: not a {SHARDS_FORMAT!r} manifest")
    shards = man.get("shards") or {}
    if not isinstance(shards, dict) or not all(isinstance(e, dict) for e in shards.values()):
        raise ValueError(f"{man_path}: 'shards' must map each shard's name to its entry")
    if not man.get("complete"):
        rep.fail(str(man_path), "the run is not complete (resume it with --resume)")
    idx_path = dataset / "subjects" / "index.json"
    try:
        for sid, digest in json.loads(idx_path.read_text())["subjects"].items():
            p = dataset / "subjects" / f"{sid}.npz"
            if not p.is_file() or sha256_file(p) != digest:
                rep.fail(str(p), "missing or its SHA-256 differs from subjects/index.json")
    except (OSError, ValueError, KeyError, TypeError, AttributeError) as exc:
        rep.fail(str(idx_path), f"unreadable subject index ({exc})")
    rebuild = MeshRebuilder(dataset, man.get("config", {}))
    m = rebuild.model
    from synth.labels import bone_parts

    bone_to_part = bone_parts(m.vertex_bones.numpy(), m.vertex_parts.numpy(), m.num_joints)
    for name, entry in sorted(shards.items()):
        path = dataset / name
        if not path.is_file():
            rep.fail(str(path), "missing shard")
            continue
        if sha256_file(path) != entry.get("sha256"):
            rep.fail(str(path), "SHA-256 differs from the manifest")
            continue
        samples = read_shard(path)
        if len(samples) != entry.get("samples"):
            rep.fail(str(path), f"holds {len(samples)} samples, the manifest says {entry.get('samples')}")
        docs: dict[str, dict[str, Any]] = {}
        for key, fields in sorted(samples.items()):
            where = f"{name}:{key}"
            rep.samples += 1
            try:
                docs[key] = _check_sample(where, fields, rebuild, bone_to_part, rep)
            except ValueError as exc:
                rep.fail(where, str(exc).splitlines()[0])
            if log is not None and rep.samples % 50 == 0:
                log(f"{rep.samples} samples checked, {len(rep.failures)} failures")
            if len(rep.failures) >= max_failures:
                rep.fail(str(dataset), f"stopped after {max_failures} failures")
                return rep
        seq = (man.get("config") or {}).get("sequence") or {}
        if seq.get("enabled"):
            from synth.validate_sequence import check_sequences

            for msg in check_sequences(docs, seq, entry.get("first", 0)):
                rep.fail(str(path), msg)
    return rep


def check_keypoints(cam: Camera, person: dict[str, Any]) -> list[str]:
    """What is wrong with a person's ``keypoints_3d_cam`` and ``keypoints_2d`` against the stored
    ``keypoints_3d`` and camera, beyond the JSON's rounding (:mod:`synth.dataset.format`, Precision)."""
    out = []
    kp3 = np.asarray(person["keypoints_3d"], np.float64)
    kc = kp3 @ cam.R.T + cam.t
    err3 = np.abs(kc - np.asarray(person["keypoints_3d_cam"], np.float64)).max(-1)
    tol3 = fmt.camera_point_tolerance(kp3, cam.R)
    if (err3 > tol3).any():
        k = int(np.argmax(err3 - tol3))
        out.append(f"keypoints_3d_cam is not R keypoints_3d + t ({err3[k]:.2e} m at keypoint {k}, allowed {tol3[k]:.1e})")
    front = kc[:, 2] > 1e-6
    if front.any():
        kp2 = np.asarray(person["keypoints_2d"], np.float64)[front]
        err = np.abs(cam.project(kp3[front]) - kp2).max(-1)
        tol = fmt.projection_tolerance(kp3[front], cam.K, cam.R, cam.t)
        if (err > tol).any():
            k = int(np.argmax(err - tol))
            out.append(f"keypoints_2d are not the projection of keypoints_3d ({err[k]:.2e} px, allowed {tol[k]:.1e})")
    return out


def check_correspondences(
    cam: Camera, verts: np.ndarray, faces: np.ndarray, corr: np.ndarray, depth: np.ndarray, sel: np.ndarray
) -> list[str]:
    """What is wrong with the correspondences ``corr`` (H, W, 3) and ``depth`` (H, W) of the pixels
    ``sel`` (H, W) bool of one person against its rebuilt mesh (``verts`` (V, 3) world, ``faces``),
    all of it in front of the camera: a face index outside the mesh, a point that does not project
    onto its pixel's centre (:func:`synth.dataset.format.correspondence_tolerance`), a depth that is not the
    point's."""
    f = corr[..., 0][sel].astype(np.int64)
    if f.size == 0:
        return []
    if f.min() < 0 or f.max() >= len(faces):
        return ["correspondence face index outside the mesh"]
    out = []
    tri = verts[faces[f]]
    bc = corr[..., 1:][sel].astype(np.float64)
    bc = np.concatenate([1 - bc.sum(1, keepdims=True), bc], 1)
    pts = np.einsum("nkc,nk->nc", tri, bc)
    ys, xs = np.nonzero(sel)
    err = np.abs(cam.project(pts) - np.stack([xs + 0.5, ys + 0.5], 1)).max(-1)
    normals = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    tol = fmt.correspondence_tolerance(pts, normals, cam.K, cam.R, cam.t)
    if (err > tol).any():
        k = int(np.argmax(err - tol))
        out.append(
            f"correspondences reproject {err[k]:.2e} px from their pixel centres "
            f"(pixel ({xs[k]}, {ys[k]}), allowed {tol[k]:.1e})"
        )
    derr = np.abs((pts @ cam.R.T + cam.t)[:, 2] - depth[sel]).max()
    if derr > DEPTH_M:
        out.append(f"depth differs from the correspondences by {derr * 1000:.3f} mm")
    return out


def occluder_coverage(occluders: list[dict[str, Any]], cam: Camera, w: int, h: int) -> np.ndarray:
    """(H, W) bool: pixel centres inside the projection of the sample's occluders (their parts in
    front of the camera; an occluder crossing the camera plane covers every pixel it may)."""
    from synth.occluders import Occluder, occluder_mesh

    out = np.zeros((h, w), bool)
    for d in occluders:
        v, f, _ = occluder_mesh(Occluder.from_json(d))
        if (v @ cam.R.T + cam.t)[:, 2].min() <= 1e-3:
            return np.ones((h, w), bool)
        out |= coverage(cam.project(v), f, w, h)
    return out


def check_cloth_bones(corr: np.ndarray, bones: np.ndarray, sel: np.ndarray, first: int, body_bones: np.ndarray) -> list[str]:
    """A person's pixels ``sel`` on its cloth layer (correspondence faces ``first`` to ``first + F``)
    must carry the bone of the body face under them (layer face ``f`` lies over body face ``f``)."""
    f = corr[..., 0][sel].astype(np.int64)
    on = (f >= first) & (f < first + len(body_bones))
    want = body_bones[f[on] - first] + 1
    bad = int((bones[sel][on] != want).sum())
    return [f"{bad} cloth pixels do not carry the bone of the body under them"] if bad else []


def check_topology(rebuild: MeshRebuilder, person: dict[str, Any], sample: dict[str, Any], i: int) -> list[str]:
    """Person ``i``'s ``vertices_<name>`` rebuilt by the reparameterised model from the stored parameters
    (:mod:`synth.topology`), within ``TOPOLOGY_M``; a member without ``labels.topology`` is an error."""
    names = [k for k in sample if k.startswith("vertices_")]
    if rebuild.topology is None:
        return [f"{names[0]} present but the config has no labels.topology"] if names and i == 0 else []
    key = f"vertices_{rebuild.topology.name}"
    got = sample.get(key)
    if got is None or got.ndim != 3 or i >= len(got) or got.shape[1:] != (rebuild.topology.model.num_vertices, 3):
        return [f"{key} missing or not (P, {rebuild.topology.model.num_vertices}, 3)"]
    b = person["blsm"]
    want = rebuild.topology.vertices(rebuild.subjects[person["subject"]].registration, *(np.asarray(b[k], np.float32) for k in ("pose", "global_orient", "transl")))
    err = float(np.abs(got[i] - want).max())
    return [f"{key} differs from the rebuilt body by {err * 1000:.3f} mm"] if err > TOPOLOGY_M else []


def _check_sample(where: str, fields: dict[str, bytes], rebuild: MeshRebuilder, bone_to_part: np.ndarray,
                  rep: Report) -> dict[str, Any] | None:
    """Check one sample (module docstring); return its labels (None when they cannot be read)."""
    missing = [f for f in fmt.FIELDS if f not in fields]
    if missing:
        rep.fail(where, f"missing fields {missing}")
        return None
    s = fmt.decode_sample(fields, where)
    doc = s["json"]
    w, h = doc["image"]["width"], doc["image"]["height"]
    for k, shape in (("rgb", (h, w, 3)), ("mask", (h, w)), ("parts", (h, w)), ("bones", (h, w)), ("depth", (h, w)), ("corr", (h, w, 3))):
        if s[k].shape != shape:
            rep.fail(where, f"{k} has shape {s[k].shape}, expected {shape}")
            return doc
    cam = Camera(K=np.array(doc["camera"]["K"]), R=np.array(doc["camera"]["R"]), t=np.array(doc["camera"]["t"]), width=w, height=h)
    mask, depth, corr = s["mask"], s["depth"], s["corr"]
    fg = mask > 0
    if not np.array_equal(fg, s["bones"] > 0) or not np.array_equal(fg, depth > 0):
        rep.fail(where, "mask, bones and depth disagree on which pixels show a person")
    ok_parts = np.where(fg, bone_to_part[np.maximum(s["bones"].astype(np.int64) - 1, 0)] + 1, 0)
    if not np.array_equal(ok_parts, s["parts"]):
        rep.fail(where, "parts do not follow the bones' parts")
    union = np.zeros((h, w), bool)
    bodies = []  # (vertices, faces, vertex parts) of each person's body: contacts, occupancy
    for i, p in enumerate(doc["people"]):
        pw = f"{where} person {i}"
        kp3 = np.asarray(p["keypoints_3d"], np.float64)
        for msg in check_keypoints(cam, p):
            rep.fail(pw, msg)
        kp2 = np.asarray(p["keypoints_2d"], np.float64)
        sel = mask == i + 1
        vis = np.asarray(p["visible"], bool)
        if (vis & ~np.asarray(p["in_frame"], bool)).any():
            rep.fail(pw, "a visible keypoint is not in frame")
        px = np.floor(kp2[vis]).astype(np.int64)
        inside = (px[:, 0] >= 0) & (px[:, 0] < w) & (px[:, 1] >= 0) & (px[:, 1] < h)
        if not inside.all() or not sel[px[:, 1], px[:, 0]].all():
            rep.fail(pw, "a visible keypoint lies outside the person's mask")
        if sel.any():
            ys, xs = np.nonzero(sel)
            box = [int(xs.min()), int(ys.min()), int(xs.max()) + 1, int(ys.max()) + 1]
            if p["box"] != box:
                rep.fail(pw, f"box {p['box']} is not the mask's box {box}")
            if vis.any():
                b = p["box"]
                if not ((kp2[vis, 0] >= b[0]).all() and (kp2[vis, 0] <= b[2]).all() and (kp2[vis, 1] >= b[1]).all() and (kp2[vis, 1] <= b[3]).all()):
                    rep.fail(pw, "box does not hold the visible keypoints")
        elif p["box"] is not None or vis.any():
            rep.fail(pw, "no mask pixels but a box or visible keypoints")
        verts, faces, kp_re = rebuild.mesh(p)
        for msg in check_topology(rebuild, p, s, i):
            rep.fail(pw, msg)
        nb = len(rebuild.bones)
        bodies.append((verts[:nb], rebuild.body_faces, bone_to_part[np.asarray(rebuild.bones)]))
        if np.abs(kp_re - kp3).max() > 1e-4:
            rep.fail(pw, f"keypoints_3d differ from the rebuilt body by {np.abs(kp_re - kp3).max() * 1000:.2f} mm")
        if "contact" in p:
            from synth.validate_sequence import check_contact

            for msg in check_contact(rebuild.model, rebuild.bones, verts[: len(rebuild.bones)], kp_re, p, doc,
                                     rebuild.regions):
                rep.fail(pw, msg)
        vc = verts @ cam.R.T + cam.t
        if (vc[:, 2] <= 1e-3).any():
            continue  # a mesh crossing the camera plane cannot be projected as triangles
        union |= coverage(cam.project(verts), faces, w, h)
        if rebuild.cloth is not None:
            for msg in check_cloth_bones(corr, s["bones"], sel, *rebuild.cloth):
                rep.fail(pw, msg)
        for msg in check_correspondences(cam, verts, faces, corr, depth, sel):
            rep.fail(pw, msg)
    for msg in _check_body_labels(doc, s, bodies, rebuild, cam):
        rep.fail(where, msg)
    hidden = occluder_coverage(doc.get("occluders") or [], cam, w, h)
    diff = int(((union ^ fg) & ~(union & hidden)).sum())
    if diff > max(2, EDGE_PIXELS * fg.sum()):
        rep.fail(where, f"the mask differs from the projected meshes in {diff} of {int(fg.sum())} pixels")
    return doc


def _check_body_labels(doc: dict[str, Any], s: dict[str, Any], bodies: list, rebuild: MeshRebuilder, cam: Camera) -> list[str]:
    """``contacts`` and ``occupancy`` (:mod:`synth.contacts`) recomputed from the rebuilt bodies;
    either present without its config key is an error."""
    from synth.contacts import check_contacts, check_occupancy

    msgs = []
    if rebuild.contact_distance:
        msgs += check_contacts(doc, bodies)
        got = {float(e.get("distance", -1)) for e in doc.get("contacts") or []}
        if got - {rebuild.contact_distance}:
            msgs.append(f"contacts use distance {sorted(got)}, the config says {rebuild.contact_distance}")
    elif "contacts" in doc:
        msgs.append("contacts present but the config has no labels.contact_distance")
    if rebuild.occupancy:
        msgs += check_occupancy(s.get("occupancy"), doc, bodies, rebuild.occupancy, cam.R, cam.t)
    elif "occupancy" in s:
        msgs.append("occupancy.npy.gz present but the config has no labels.occupancy")
    return msgs
