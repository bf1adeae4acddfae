"""Which true surface vertices a camera sees (checks of the simulator's variants).

A vertex is seen when it projects inside the image (with the camera's distortion), lies in
front of the camera, faces it, and no other part of the tissue is in the way (a ray cast).
"""

from __future__ import annotations

import numpy as np

from ..core.geometry.cameras import CameraModel, in_image, project
from .render import cast_rays, mesh_scene
from .scene import vertex_normals


def visible_vertices(
    vertices: np.ndarray, faces: np.ndarray, camera: CameraModel, cam_to_world: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Seen mask (V,) bool and depth (V,) m (camera z) of vertices (V, 3) in one camera."""
    uv, depth = project(vertices, cam_to_world, camera)
    origin = cam_to_world[:3, 3]
    normals = vertex_normals(vertices, faces)
    seen = in_image(uv, camera) & (depth > 0) & (((origin - vertices) * normals).sum(1) > 0)
    if seen.any():
        scene = mesh_scene(vertices, faces)
        idx = np.flatnonzero(seen)
        ray = vertices[idx] - origin
        dist = np.linalg.norm(ray, axis=1)
        rays = np.column_stack([np.broadcast_to(origin, ray.shape), ray / dist[:, None]])
        t_hit = cast_rays(scene, rays)["t_hit"].numpy()
        seen[idx] = t_hit >= dist - 2e-4  # nothing closer than the vertex itself (0.2 mm)
    return seen, depth
