"""The scene: triangles (one triangle = one patch) with RGB reflectance and emission.

Loaders (:mod:`blockray.host_driver.objload`) and built-in scenes
(:mod:`blockray.host_driver.builtin`) produce a :class:`Scene`; everything downstream reads it.
"""

from dataclasses import dataclass, field
from functools import cached_property

import numpy as np

__all__ = ["Camera", "Scene"]


@dataclass(frozen=True)
class Camera:
    """A pinhole camera. ``fov`` is the vertical field of view in degrees."""
    position: tuple
    look_at: tuple
    up: tuple = (0.0, 1.0, 0.0)
    fov: float = 40.0


@dataclass(eq=False)
class Scene:
    name: str
    vertices: np.ndarray        # (V, 3) float64
    triangles: np.ndarray       # (N, 3) int64 indices into vertices; one triangle is one patch
    reflectance: np.ndarray     # (N, 3) float64, RGB, each in [0, 1)
    emission: np.ndarray        # (N, 3) float64, RGB, >= 0
    group: np.ndarray           # (N,) int64 index into group_names (the OBJ `o`/`g` a patch came from)
    group_names: list = field(default_factory=list)
    camera: Camera | None = None
    source: str = ""            # file path, or "builtin:NAME"

    @property
    def patches(self):
        return len(self.triangles)

    @cached_property
    def patch_vertices(self):
        """(N, 3, 3) float64: the three corners of each patch."""
        return self.vertices[self.triangles]

    @cached_property
    def cross(self):
        v = self.patch_vertices
        return np.cross(v[:, 1] - v[:, 0], v[:, 2] - v[:, 0])

    @cached_property
    def areas(self):
        return 0.5 * np.linalg.norm(self.cross, axis=1)

    @cached_property
    def normals(self):
        """Unit normals (right-handed in vertex order V0, V1, V2)."""
        c = self.cross
        norm = np.linalg.norm(c, axis=1, keepdims=True)
        return np.divide(c, norm, out=np.zeros_like(c), where=norm > 0)

    @cached_property
    def centroids(self):
        return self.patch_vertices.mean(axis=1)

    @property
    def bbox(self):
        used = self.vertices[np.unique(self.triangles)] if self.patches else self.vertices
        return used.min(axis=0), used.max(axis=0)
