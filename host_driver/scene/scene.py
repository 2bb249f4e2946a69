"""The scene: triangles (one triangle = one patch) with RGB reflectance and emission.

Loaders (:mod:`blockray.host_driver.scene.objload`) and built-in scenes
(:mod:`blockray.host_driver.scene.builtin`) produce a :class:`Scene`; everything downstream reads it.
"""

from dataclasses import dataclass, field
from functools import cached_property

import numpy as np

from blockray.errors import SceneError

__all__ = ["COORDINATE_LIMIT", "MIN_EXTENT", "Camera", "Scene", "check_range"]

#: Largest coordinate magnitude and smallest scene extent (largest side of the bounding box)
#: accepted. The host and the golden board compute in float64 with products of up to 8 coordinate
#: differences (squared cross products for areas, orient3d, r**4 of the form factors); within
#: these bounds every such product, (2e30)**8 ~ 3e243 down to (1e-30)**8 = 1e-240, is a normal
#: float64 (1.8e308 .. 2.2e-308), so areas cannot overflow to inf or underflow to 0. The
#: hardware boards quantise the bounding box to B-bit integers and are scale-free.
COORDINATE_LIMIT = 1e30
MIN_EXTENT = 1e-30


def check_range(vertices, *, path=None):
    """Raise :class:`SceneError` unless ``vertices`` lie within the range the boards compute in
    (see :data:`COORDINATE_LIMIT` and :data:`MIN_EXTENT`)."""
    v = np.asarray(vertices, dtype=np.float64)
    if v.size == 0:
        return
    if not np.all(np.abs(v) <= COORDINATE_LIMIT):          # also NaN
        raise SceneError(f"a vertex coordinate is beyond +-{COORDINATE_LIMIT:g} or not finite "
                         "(scale the scene down)", path=path)
    extent = float(np.max(v.max(axis=0) - v.min(axis=0)))
    if not extent >= MIN_EXTENT:
        raise SceneError(f"the scene's extent {extent:.3g} is below {MIN_EXTENT:g}, the smallest the "
                         "boards compute with (scale the scene up)", path=path)


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
    contact: dict | None = None # what load_scene's contact-line split did (host_driver/scene/contact.py)

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
