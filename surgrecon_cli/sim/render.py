"""Ray-cast rendering of the tissue and tool (Open3D `RaycastingScene`, one ray per pixel).

Rays go through the *distorted* pixel centres (undistorted with the plumb_bob model), so
the image carries the camera's lens distortion. Shading: the endoscope's light sits at the
camera; Lambert diffuse with inverse-square falloff, a Blinn-Phong specular lobe (wet
tissue, metallic tool), then Gaussian pixel noise.
"""

from __future__ import annotations

import numpy as np
import open3d as o3d

from ..core.geometry.cameras import CameraModel, pixel_rays
from .texture import Texture

TISSUE, TOOL = 0, 1
CPU = o3d.core.Device("CPU:0")


def mesh_scene(vertices: np.ndarray, faces: np.ndarray) -> o3d.t.geometry.RaycastingScene:
    """A ray-casting scene holding one triangle mesh: vertices (V, 3) m, faces (F, 3)."""
    mesh = o3d.t.geometry.TriangleMesh()
    mesh.vertex.positions = o3d.core.Tensor(vertices.astype(np.float32), o3d.core.float32, CPU)
    mesh.triangle.indices = o3d.core.Tensor(faces.astype(np.int32), o3d.core.int32, CPU)
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(mesh)
    return scene


def cast_rays(scene: o3d.t.geometry.RaycastingScene, rays: np.ndarray
              ) -> dict[str, o3d.core.Tensor]:
    """The scene's hits (open3d's `cast_rays` result) for rays (N, 6): origin, unit direction."""
    return scene.cast_rays(o3d.core.Tensor(rays.astype(np.float32), o3d.core.float32, CPU))


def pixel_grid(camera: CameraModel) -> np.ndarray:
    """All pixel centres (H*W, 2) in row-major order."""
    u, v = np.meshgrid(np.arange(camera.width), np.arange(camera.height))
    return np.stack([u.ravel(), v.ravel()], 1).astype(np.float64)


def tool_mesh(
    tip: np.ndarray, axis: np.ndarray, radius: float, length: float
) -> o3d.t.geometry.TriangleMesh:
    """The shaft: a cylinder from the tip along `axis`, with a hemispherical end at the tip."""
    cyl = o3d.geometry.TriangleMesh.create_cylinder(
        radius=radius, height=length, resolution=48, split=4
    )
    cyl.translate([0, 0, length / 2 + radius])
    cap = o3d.geometry.TriangleMesh.create_sphere(radius=radius, resolution=24)
    cap.translate([0, 0, radius])
    shaft = cyl + cap
    z = axis / np.linalg.norm(axis)
    x = np.cross([0.0, 1.0, 0.0], z)
    x /= np.linalg.norm(x)
    R = np.column_stack([x, np.cross(z, x), z])
    shaft.rotate(R, center=np.zeros(3))
    shaft.translate(tip)
    return o3d.t.geometry.TriangleMesh.from_legacy(shaft)


class Renderer:
    """Renders one camera's view of the tissue (+ tool) at one instant."""

    def __init__(self, texture: Texture, noise: float, rng: np.random.Generator):
        self.texture = texture
        self.noise = noise
        self.rng = rng
        self._rays_cache: dict[int, np.ndarray] = {}

    def _camera_rays(self, key: int, camera: CameraModel) -> np.ndarray:
        """Unit ray directions (H*W, 3) in the camera frame, cached per camera."""
        if key not in self._rays_cache:
            _, d = pixel_rays(pixel_grid(camera), camera, np.eye(4))
            self._rays_cache[key] = d
        return self._rays_cache[key]

    def render(
        self,
        key: int,
        camera: CameraModel,
        cam_to_world: np.ndarray,
        vertices: np.ndarray,
        normals: np.ndarray,
        faces: np.ndarray,
        material_xy: np.ndarray,
        tool: o3d.t.geometry.TriangleMesh | None,
    ) -> np.ndarray:
        """RGB uint8 image (H, W, 3)."""
        scene = mesh_scene(vertices, faces)
        if tool is not None:
            scene.add_triangles(tool)
        origin = cam_to_world[:3, 3]
        dirs = self._camera_rays(key, camera) @ cam_to_world[:3, :3].T
        hit = cast_rays(scene, np.concatenate([np.broadcast_to(origin, dirs.shape), dirs], 1))
        t_hit = hit["t_hit"].numpy()
        geom = hit["geometry_ids"].numpy()
        prim = hit["primitive_ids"].numpy()
        uvs = hit["primitive_uvs"].numpy().astype(np.float64)
        face_normals = hit["primitive_normals"].numpy().astype(np.float64)

        color = np.full((len(dirs), 3), 0.03)
        view = -dirs
        # Tissue: texture colour, interpolated vertex normals.
        on_tissue = np.isfinite(t_hit) & (geom == TISSUE)
        f = faces[prim[on_tissue]]
        b = np.column_stack([1 - uvs[on_tissue].sum(1), uvs[on_tissue]])
        mat = np.einsum("nk,nkd->nd", b, material_xy[f])
        n = np.einsum("nk,nkd->nd", b, normals[f])
        n /= np.linalg.norm(n, axis=1, keepdims=True)
        albedo = self.texture.sample(mat)
        wet = 0.35 + 0.65 * albedo[:, 1]  # glossier on pale tissue, a patchy wet look
        color[on_tissue] = self._shade(
            albedo, n, view[on_tissue], t_hit[on_tissue], 0.55 * wet, 80.0
        )
        # Tool: brushed metal.
        on_tool = np.isfinite(t_hit) & (geom == TOOL)
        if on_tool.any():
            n = face_normals[on_tool]
            n *= np.where((n * view[on_tool]).sum(1, keepdims=True) < 0, -1.0, 1.0)
            albedo = np.full((on_tool.sum(), 3), [0.62, 0.63, 0.66])
            color[on_tool] = self._shade(albedo, n, view[on_tool], t_hit[on_tool], 0.45, 25.0)
        image = color * 255.0 + self.rng.normal(0.0, self.noise, color.shape)
        return image.clip(0, 255).astype(np.uint8).reshape(camera.height, camera.width, 3)

    @staticmethod
    def _shade(albedo, normal, view, dist, specular, shininess):
        """Light at the camera: Lambert with 1/d² falloff (1 at 45 mm) + Blinn-Phong specular."""
        cos = (normal * view).sum(1).clip(0, 1)
        falloff = (0.045 / np.maximum(dist, 1e-3)) ** 2
        diffuse = albedo * (0.15 + 0.95 * cos * falloff)[:, None]
        highlight = (specular * cos**shininess * falloff)[:, None]
        return (diffuse + highlight).clip(0, 1)
