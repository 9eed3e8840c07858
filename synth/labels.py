"""Per-pixel and per-person labels from one render (:class:`synth.render.Frame`).

Everything here is computed from the label pass (the first hit of the ray through each pixel
centre) and the people's posed meshes, so masks, parts, depth, correspondences, keypoint
visibility and boxes describe the same geometry as the RGB.

Keypoint visibility: keypoint k of person p is *visible* when it is in front of the camera, its
pixel ``(floor(u), floor(v))`` is inside the image, and the ray through that pixel first hits
person p on a face of the keypoint's own body region (its bone, the bone's parent and children for
joint keypoints; the bones of its vertices for surface keypoints), at a depth consistent with the
keypoint: for a surface keypoint within ``SURFACE_TOL`` of it, for a joint (inside the body) in
front of it by less than ``JOINT_DEPTH``. A keypoint hidden by the body itself (an arm behind the
torso, the far ear) or by another person is therefore not visible. Hair (:mod:`synth.hair`) is part
of its person and of the head: it hides the surface keypoints under it (an ear under long hair) and
counts as the head's surface for the joints inside the head. Clothes (:mod:`synth.garments`) are
part of their person and of the bone of the body under them, and count as the body's surface (a
clothed elbow or hip is visible, as annotators of photographs mark it).
"""

from __future__ import annotations

import numpy as np

from blsm.camera import Camera
from blsm.mesh import barycentric
from synth.render import Frame

SURFACE_TOL = 0.05  # metres
JOINT_DEPTH = 0.3  # metres: no limb or trunk is thicker in front of its joint
JOINT_BEHIND = 0.02  # metres: round-off allowance for a joint right at the surface
HIT_TOL = 1e-3  # metres: a hit point this close to a person's face (plane distance) is on it


def face_bones(faces: np.ndarray, weights: np.ndarray) -> np.ndarray:
    """(F,) the bone of largest summed skinning weight over each face's three vertices."""
    return weights[faces].sum(1).argmax(1)


def bone_parts(vertex_bones: np.ndarray, vertex_parts: np.ndarray, num_bones: int) -> np.ndarray:
    """(J,) the part of each bone: the most frequent part of the model vertices it drives most."""
    table = np.zeros((num_bones, int(vertex_parts.max()) + 1), np.int64)
    np.add.at(table, (vertex_bones, vertex_parts), 1)
    return table.argmax(1)


def keypoint_regions(
    keypoint_joint: np.ndarray, keypoint_vertices: np.ndarray, vertex_bones: np.ndarray, parents: list[int]
) -> list[set[int]]:
    """The bones whose faces may show each keypoint (see the module docstring)."""
    children: dict[int, list[int]] = {j: [] for j in range(len(parents))}
    for c, p in enumerate(parents):
        if p >= 0:
            children[p].append(c)
    out = []
    for k, j in enumerate(keypoint_joint):
        if j >= 0:
            s = {int(j), *children[int(j)]}
            if parents[j] >= 0:
                s.add(parents[j])
        else:
            s = {int(b) for b in vertex_bones[keypoint_vertices[k]]}
        out.append(s)
    return out


def assign_hits(frame: Frame, meshes: list[tuple[np.ndarray, np.ndarray]]) -> tuple[np.ndarray, np.ndarray]:
    """Which mesh each hit pixel shows, and the barycentric coordinates of the hit.

    The label pass gives the hit's world position and face index; the mesh is the one whose face
    of that index contains the hit point (the smallest distance to the face's plane, which is ~0
    for the right one).

    Returns:
        the index into ``meshes`` (H, W) int64 (-1 where nothing is hit) and bary (H, W, 3) float32.
    """
    h, w = frame.hit.shape
    person = np.full((h, w), -1, np.int64)
    bary = np.zeros((h, w, 3), np.float32)
    idx = np.flatnonzero(frame.hit)
    if idx.size == 0:
        return person, bary
    f = frame.face.reshape(-1)[idx]
    p = frame.position.reshape(-1, 3)[idx].astype(np.float64)
    best = np.full(idx.size, np.inf)
    best_b = np.zeros((idx.size, 3))
    best_p = np.full(idx.size, -1)
    for i, (verts, faces) in enumerate(meshes):
        ok = f < len(faces)
        tri = verts[faces[np.where(ok, f, 0)]].astype(np.float64)  # (N, 3, 3)
        e1, e2, d = tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0], p - tri[:, 0]
        n = np.cross(e1, e2)
        nn = np.linalg.norm(n, axis=1)
        dist = np.abs(np.einsum("nc,nc->n", d, n)) / np.maximum(nn, 1e-20)
        b = barycentric(tri, p)
        outside = np.clip(-b, 0, None).sum(1)  # 0 inside the triangle
        score = dist + outside * np.sqrt(nn)  # a point off the triangle is far from it
        better = ok & (score < best)
        best = np.where(better, score, best)
        best_b[better] = b[better]
        best_p[better] = i
    best_p[best > HIT_TOL] = -1  # no person's face holds the hit: reported as unassigned
    flat_p = person.reshape(-1)
    flat_p[idx] = best_p
    bary.reshape(-1, 3)[idx] = best_b
    return person, bary


def _box_full(p: dict, camera: Camera) -> list[float] | None:
    """The box of person ``p``'s projected mesh: from its hull points ("outline", see
    :func:`synth.camera.outline_index`) when all of them are in front of the camera (then the whole
    mesh is, and the extremes are the same); otherwise from every vertex in front; None for a
    person wholly behind the camera (a sequence's camera can pass people by)."""
    pts = np.asarray(p.get("outline", p["vertices"]), np.float64)
    z = camera.world_to_camera(pts)[:, 2]
    if z.min() <= 1e-6:
        pts = np.asarray(p["vertices"], np.float64)
        z = camera.world_to_camera(pts)[:, 2]
    if not (z > 1e-6).any():
        return None
    pv = camera.project(pts[z > 1e-6])
    return [float(pv[:, 0].min()), float(pv[:, 1].min()), float(pv[:, 0].max()), float(pv[:, 1].max())]


def _hit_meshes(people: list[dict]) -> tuple[list, list[int], list[int], list[np.ndarray], list[bool]]:
    """The meshes a hit can be on: every body, then every hair, cloth layer and skirt. Per mesh:
    (vertices, faces), its person, the offset of its faces in the person's correspondence
    numbering (body, hair, layer, skirt), each face's bone, and whether it is hair."""
    entries = [(p["vertices"], p["faces"]) for p in people]
    owner, offset = list(range(len(people))), [0] * len(people)
    face_bones, is_hair = [np.asarray(p["face_bones"]) for p in people], [False] * len(people)
    for i, p in enumerate(people):
        nb = len(p["faces"])
        nh = len(p["hair_faces"]) if p.get("hair_vertices") is not None else 0
        extra = []
        if nh:
            extra.append((p["hair_vertices"], p["hair_faces"], 0, np.full(nh, p.get("hair_bone", 0)), True))
        if p.get("cloth_vertices") is not None:
            extra.append((p["cloth_vertices"], p["faces"], nb + nh, face_bones[i], False))
        if p.get("skirt_vertices") is not None:
            extra.append((p["skirt_vertices"], p["skirt_faces"], 2 * nb + nh, np.asarray(p["skirt_face_bones"]), False))
        for v, f, off, fb, hair in extra:
            entries.append((v, f))
            owner.append(i)
            offset.append(nb if hair else off)
            face_bones.append(fb)
            is_hair.append(hair)
    return entries, owner, offset, face_bones, is_hair


def person_labels(
    frame: Frame,
    camera: Camera,
    people: list[dict],
    bone_to_part: np.ndarray,
    regions: list[set[int]],
    keypoint_is_joint: np.ndarray,
    occluders: list[tuple[np.ndarray, np.ndarray]] = (),
) -> dict:
    """All label images and per-person keypoint/box labels of one frame.

    Args:
        frame: the render.
        camera: its camera.
        people: per person ``vertices`` (V, 3), ``faces`` (F, 3), ``face_bones`` (F,), ``keypoints``
            (K, 3) world, and optionally a hair (:mod:`synth.hair`): ``hair_vertices`` (H, 3),
            ``hair_faces`` (Fh, 3) and ``hair_bone`` (the head's bone index). A hair pixel belongs to
            its person's mask, to the head bone and part; its depth is the hair's; its
            correspondence face is ``F + f`` for hair face ``f`` (the person's rendered mesh is the
            body followed by the hair); it hides the surface keypoints under it (eyes, ears) but
            not the joints inside the head. Optionally clothes (:mod:`synth.garments`):
            ``cloth_vertices`` (V, 3), the cloth layer over the body's faces (a pixel on layer face
            ``f`` gets body face ``f``'s bone; correspondence face ``F + Fh + f``), and a skirt:
            ``skirt_vertices``, ``skirt_faces`` (Fs, 3) and ``skirt_face_bones`` (Fs,)
            (correspondence face ``F + Fh + F + f``). Clothes are the person's surface for keypoint
            visibility.
        bone_to_part: (J,) part index per bone.
        regions: per keypoint, the bones that may show it.
        keypoint_is_joint: (K,) bool.
        occluders: (vertices, faces) of objects in the scene that belong to no person
            (:mod:`synth.occluders`): their pixels are background in every label, and a keypoint
            whose pixel shows one is not visible.

    Returns:
        ``mask``, ``parts``, ``bones`` (H, W) uint8; ``depth`` (H, W) float32; ``corr`` (H, W, 3)
        float32; ``people``: per person ``keypoints_2d``, ``keypoints_3d_cam``, ``visible``,
        ``in_frame``, ``box``, ``box_full``, ``pixels``; ``unassigned`` (hit pixels no person's face
        contains: should be 0).
    """
    h, w = frame.hit.shape
    entries, owner, offset, face_bones, is_hair = _hit_meshes(people)
    entries += list(occluders)
    owner += [-1] * len(occluders)
    offset += [0] * len(occluders)
    entry, bary = assign_hits(frame, entries)
    assigned = entry >= 0
    e = np.maximum(entry, 0)
    person = np.where(assigned, np.asarray(owner)[e], -1)
    hit = person >= 0  # a person's pixel (an occluder's is background)
    entry = np.where(hit, entry, -1)
    on_hair = hit & np.asarray(is_hair + [False] * len(occluders))[e]
    face = np.where(hit, frame.face + np.asarray(offset)[e], -1)
    mask = np.where(hit, person + 1, 0).astype(np.uint8)
    bones = np.zeros((h, w), np.uint8)
    for k, fb in enumerate(face_bones):
        sel = entry == k
        bones[sel] = fb[frame.face[sel]] + 1
    parts = np.where(hit, bone_to_part[np.maximum(bones.astype(np.int64) - 1, 0)] + 1, 0).astype(np.uint8)
    depth = np.zeros((h, w), np.float32)
    depth[hit] = (frame.position[hit].astype(np.float64) @ camera.R[2] + camera.t[2]).astype(np.float32)
    corr = np.zeros((h, w, 3), np.float32)
    corr[..., 0] = face
    corr[..., 1:] = np.where(hit[..., None], bary[..., 1:], 0.0)

    out_people = []
    for i, p in enumerate(people):
        kp = np.asarray(p["keypoints"], np.float64)
        kc = kp @ camera.R.T + camera.t
        front = kc[:, 2] > 1e-6
        uv = np.full((len(kp), 2), np.nan)
        uv[front] = camera.project(kp[front])
        px = np.floor(np.nan_to_num(uv, nan=-1.0)).astype(np.int64)
        in_frame = front & (px[:, 0] >= 0) & (px[:, 0] < w) & (px[:, 1] >= 0) & (px[:, 1] < h)
        visible = np.zeros(len(kp), bool)
        for k in np.flatnonzero(in_frame):
            u, v = px[k]
            if person[v, u] != i or (int(bones[v, u]) - 1) not in regions[k]:
                continue
            if on_hair[v, u] and not keypoint_is_joint[k]:  # a surface point under hair is hidden
                continue
            dz = kc[k, 2] - depth[v, u]  # > 0: the surface is in front of the keypoint
            if keypoint_is_joint[k]:
                visible[k] = -JOINT_BEHIND <= dz < JOINT_DEPTH
            else:
                visible[k] = abs(dz) < SURFACE_TOL
        sel = person == i
        if sel.any():
            ys, xs = np.nonzero(sel)
            box = [int(xs.min()), int(ys.min()), int(xs.max()) + 1, int(ys.max()) + 1]
        else:
            box = None
        box_full = _box_full(p, camera)
        out_people.append(
            {
                "keypoints_2d": np.where(np.isnan(uv), 0.0, uv),
                "keypoints_3d_cam": kc,
                "visible": visible,
                "in_frame": in_frame,
                "box": box,
                "box_full": box_full,
                "pixels": int(sel.sum()),
            }
        )
    unassigned = int((frame.hit & ~assigned).sum())
    return {
        "mask": mask,
        "parts": parts,
        "bones": bones,
        "depth": depth,
        "corr": corr,
        "people": out_people,
        "unassigned": unassigned,
    }
