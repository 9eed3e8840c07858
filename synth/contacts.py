"""Labels of people touching each other, and of the space their bodies fill (both optional).

**Contacts** (``labels.contact_distance`` > 0, metres): the sample's JSON gets ``contacts``, one entry
per pair of people ``i < j`` (in mask order), each with

- ``people`` ``[i, j]`` and ``distance``: the contact distance used (metres);
- ``vertices``: two sorted lists, the vertices of ``i``'s body mesh (the rendered mesh:
  ``corr``'s faces index it; :func:`synth.sample.pose_person` rebuilds it) whose signed distance to
  ``j``'s body surface is at most ``distance`` (inside counts: negative), and ``j``'s to ``i``'s;
- ``parts``: the body parts (``part_names``) of those vertices, each list sorted;
- ``closest_mm``: the smallest signed vertex-to-surface distance between the two (millimetres;
  negative: the deepest vertex inside the other), or null where it is over 50 mm.

Distances are to the bodies' closed meshes (:mod:`blsm.occupancy`: exact point-triangle distances
signed by the winding number); hair and clothes are left out (their vertices are not the body's).

**Occupancy** (``labels.occupancy`` = N > 0 points a person): the sample gets ``occupancy.npy.gz``,
(P, N, 4) float32 in mask order: ``x, y, z`` in the camera frame (metres, OpenCV axes) and 1 where
the point is inside the person's body mesh, else 0. Half the points are near the surface
(surface points moved by N(0, 1 cm^2) per axis), half uniform in the body's box grown by 10 % each
side (:func:`blsm.occupancy.sample_points`, as LEAP and NASA draw them); the draw's seed is the
sample's (``seed``, ``index``), apart from its stream, so switching it on changes no other label.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from blsm import occupancy

OCCUPANCY = "occupancy.npy.gz"
REACH_M = 0.05  # closest_mm is given up to this distance (null beyond)
BOUNDARY_M = 1e-4  # validate: a vertex this close to the contact distance may fall either way


def body_labels(cfg: Any, scene: Any, bone_to_part: np.ndarray, part_names: list[str]) -> dict[str, Any]:
    """``contacts`` and ``occupancy`` (module docstring) of ``scene``'s people as ``cfg`` asks for
    them; ``bone_to_part`` maps a bone to its part."""
    bodies = [(p.vertices, p.faces, bone_to_part[np.asarray(p.vertex_bones)]) for p in scene.people]
    out: dict[str, Any] = {}
    if cfg.labels.contact_distance:
        out["contacts"] = contact_labels(bodies, part_names, cfg.labels.contact_distance)
    if cfg.labels.occupancy:
        rng = occupancy_rng(cfg.seed, scene.index)
        R, t = np.asarray(scene.camera.R, np.float64), np.asarray(scene.camera.t, np.float64)
        occ = []
        for v, f, _ in bodies:
            q = occupancy_points(v, f, cfg.labels.occupancy, rng)
            occ.append(np.concatenate([q[:, :3] @ R.T + t, q[:, 3:]], 1))
        out["occupancy"] = np.stack(occ).astype(np.float32)
    return out


def contact_labels(bodies: list[tuple[np.ndarray, np.ndarray, np.ndarray]], part_names: list[str],
                   distance: float) -> list[dict[str, Any]]:
    """The ``contacts`` of the module docstring; ``bodies``: per person (V, 3) vertices, (F, 3)
    faces and (V,) each vertex's part index."""
    out = []
    dist = [surface_distance(v, f) for v, f, _ in bodies]  # one distance structure a body, for all its pairs
    for i in range(len(bodies)):
        for j in range(i + 1, len(bodies)):
            entry: dict[str, Any] = {"people": [i, j], "distance": float(distance), "vertices": [], "parts": []}
            closest = np.inf
            for a, b in ((i, j), (j, i)):
                va, _, parts = bodies[a]
                s = signed_to(va, bodies[b], max(distance, REACH_M), dist=dist[b])
                near = np.flatnonzero(s <= distance)
                entry["vertices"].append([int(k) for k in near])
                entry["parts"].append(sorted({part_names[int(q)] for q in parts[near]}))
                closest = min(closest, float(s.min()))
            entry["closest_mm"] = round(1000.0 * closest, 3) if closest <= REACH_M else None
            out.append(entry)
    return out


def surface_distance(vertices: np.ndarray, faces: np.ndarray) -> Any:
    """``f(points) -> (N,)`` unsigned distances to one body's surface: a :class:`MeshSDF` built once
    (libigl's distance where the mesh is not closed and manifold, a scan)."""
    v = np.asarray(vertices, np.float64)
    try:
        sdf = occupancy.MeshSDF(v, faces)
    except ValueError:
        return lambda q: occupancy.distance(q, v, faces)
    return lambda q: np.abs(sdf(q)[0])


def signed_to(points: np.ndarray, body: tuple[np.ndarray, np.ndarray, np.ndarray], upper: float = np.inf,
              exact: bool = False, dist: Any = None) -> np.ndarray:
    """(N,) signed distances of ``points`` to ``body``'s surface (negative inside); with ``upper``,
    points outside the body's box grown by ``upper`` get ``+inf`` (they are farther than that).
    The distance is exact (libigl's AABB tree); the sign is the winding number's, which stays right
    where a posed body passes through itself (the pseudonormal sign does not): libigl's fast one
    (agreed with the exact one on 213,348 test points; :mod:`blsm.occupancy`) or, with ``exact``,
    the exact one (``synth validate`` checks the labels with it). ``dist``: the body's
    :func:`surface_distance`, where the caller keeps one for several queries."""
    v, f = np.asarray(body[0], np.float64), body[1]
    out = np.full(len(points), np.inf)
    sel = np.all((points >= v.min(0) - upper) & (points <= v.max(0) + upper), axis=1)
    if not sel.any():
        return out
    q = points[sel]
    d = (dist or surface_distance(v, f))(q)
    out[sel] = np.where(occupancy.inside(q, v, f, exact), -d, d)
    return out


def occupancy_points(vertices: np.ndarray, faces: np.ndarray, n: int, rng: np.random.Generator) -> np.ndarray:
    """(n, 4) world points around one body (module docstring) and whether each is inside."""
    pts = occupancy.sample_points(vertices, faces, n // 2, n - n // 2, rng)
    return np.concatenate([pts, occupancy.inside(pts, vertices, faces)[:, None]], 1)


def occupancy_rng(seed: int, index: int) -> np.random.Generator:
    # Its own stream (a four-word seed: never a sample's or a subject's).
    return np.random.Generator(np.random.PCG64(np.random.SeedSequence([int(seed), 5, int(index), 0])))


def check_contacts(doc: dict[str, Any], bodies: list[tuple[np.ndarray, np.ndarray, np.ndarray]]) -> list[str]:
    """``synth validate``: the sample's ``contacts`` recomputed from the rebuilt bodies (vertices
    within :data:`BOUNDARY_M` of the distance may fall either way)."""
    entries, part_names = doc.get("contacts"), doc["part_names"]
    n = len(bodies)
    want = {(i, j) for i in range(n) for j in range(i + 1, n)}
    if not isinstance(entries, list) or {tuple(e.get("people", ())) for e in entries} != want or len(entries) != len(want):
        return [f"contacts must hold one entry per pair of the {n} people"]
    msgs = []
    dist = [surface_distance(v, f) for v, f, _ in bodies]
    for e in entries:
        i, j = e["people"]
        d = float(e["distance"])
        for side, (a, b) in enumerate(((i, j), (j, i))):
            s = signed_to(bodies[a][0], bodies[b], max(d, REACH_M), exact=True, dist=dist[b])
            got = np.zeros(len(s), bool)
            idx = np.asarray(e["vertices"][side], np.int64)
            if idx.size and (idx.min() < 0 or idx.max() >= len(s)):
                msgs.append(f"contacts {i}-{j}: a vertex index of person {a} is out of range")
                continue
            got[idx] = True
            wrong = (got != (s <= d)) & (np.abs(s - d) > BOUNDARY_M)
            if wrong.any():
                msgs.append(f"contacts {i}-{j}: {int(wrong.sum())} vertices of person {a} are listed wrongly "
                            f"(distance {d} m)")
            if e["parts"][side] != sorted({part_names[int(q)] for q in bodies[a][2][idx]}):
                msgs.append(f"contacts {i}-{j}: the parts of person {a} are not those of its listed vertices")
    return msgs


def check_occupancy(occ: np.ndarray | None, doc: dict[str, Any], bodies: list[tuple[np.ndarray, np.ndarray, np.ndarray]],
                    n: int, cam_R: np.ndarray, cam_t: np.ndarray) -> list[str]:
    """``synth validate``: the shape of ``occupancy`` and its inside flags recomputed from the
    rebuilt bodies (points within 0.1 mm of a surface may fall either way)."""
    if occ is None:
        return [f"{OCCUPANCY} missing (the config has labels.occupancy)"]
    if occ.shape != (len(bodies), n, 4):
        return [f"{OCCUPANCY} has shape {occ.shape}, expected ({len(bodies)}, {n}, 4)"]
    msgs = []
    for i, (v, f, _) in enumerate(bodies):
        world = (occ[i, :, :3].astype(np.float64) - cam_t) @ cam_R  # camera -> world
        s = occupancy.signed_distance(world, v, f)[0]
        flag = occ[i, :, 3] > 0.5
        wrong = (flag != (s < 0)) & (np.abs(s) > BOUNDARY_M)
        if wrong.any():
            msgs.append(f"{OCCUPANCY} person {i}: {int(wrong.sum())} of {n} points flagged wrongly")
    return msgs
