"""recovery.utils.viz: the multi-person overlay's depth order and the box outlines."""

from __future__ import annotations

import numpy as np

from recovery.utils.viz import PERSON_COLORS, draw_boxes, people_overlay


def _square(cx: float, cy: float, z: float, half: float) -> np.ndarray:
    """A square facing the camera (two triangles), camera frame, metres."""
    return np.array([[cx - half, cy - half, z], [cx + half, cy - half, z], [cx + half, cy + half, z],
                     [cx - half, cy + half, z]])


def test_people_overlay_shows_the_nearer_person_whatever_the_order() -> None:
    faces = np.array([[0, 1, 2], [0, 2, 3]])
    k = np.array([[50.0, 0, 32], [0, 50.0, 32], [0, 0, 1]])
    image = np.zeros((64, 64, 3), np.uint8)
    near, far = _square(0.0, 0.0, 2.0, 0.3), _square(0.3, 0.0, 3.0, 0.6)  # overlapping on screen
    for meshes, near_index in (([near, far], 0), ([far, near], 1)):
        out = people_overlay(image, meshes, faces, k, alpha=1.0)
        centre = out[32, 32].astype(float)  # both cover it; the near one must show
        want = PERSON_COLORS[near_index]
        assert np.allclose(centre / centre.max(), want / want.max(), atol=0.05)
        right = out[32, 44].astype(float)  # only the far one covers it (near: x 25..39, far: 27..47)
        other = PERSON_COLORS[1 - near_index]
        assert np.allclose(right / right.max(), other / other.max(), atol=0.05)
        assert (out[2, 2] == 0).all()  # nobody there: the image


def test_draw_boxes_outlines_inside_the_image() -> None:
    image = np.zeros((20, 30, 3), np.uint8)
    out = draw_boxes(image, [np.array([2.0, 3.0, 12.0, 15.0]), np.array([-5.0, -5.0, 40.0, 40.0])], width=1)
    c0 = (PERSON_COLORS[0] * 255 + 0.5).astype(np.uint8)
    assert (out[3, 2:12] == c0).all() and (out[14, 2:12] == c0).all() and (out[3:15, 11] == c0).all()
    assert (out[8, 6] == 0).all()  # inside the first box, untouched
    c1 = (PERSON_COLORS[1] * 255 + 0.5).astype(np.uint8)
    assert (out[0, 15] == c1).all() and (out[19, 15] == c1).all()  # clipped to the image's edges
    assert (image == 0).all()  # the input is not changed
