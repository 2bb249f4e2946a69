"""Built-in scenes, shipped as OBJ + MTL files in ``scenes/`` and read by the ordinary loader.

``cornell``
    The Cornell box (Cornell Program of Computer Graphics' published geometry, mm) with the
    published camera: position (278, 273, -800) looking along +z, vertical field of view
    2 atan(0.0125 / 0.035) = 39.3 degrees (focal length 0.035, film 0.025). 23 polygons become
    46 triangles; the default subdivision, ``max_edge=100`` (mm), gives 928 patches.
``room``
    A furnished 6 m x 2.7 m x 5 m room in the spirit of the paper's 3013-patch room: white
    ceiling light, six yellow up-lights, table, chairs, bookshelf, sofa. The default
    subdivision, ``max_edge=0.63`` (m), gives 3040 patches (488 triangles before subdivision).

``scenes/make_scenes.py`` generates the files.
"""

import math
import os
from pathlib import Path

from ...errors import SceneError
from .contact import rounding, split_contacts
from .objload import LoadLimits, _check_max_edge, load_obj, subdivide
from .scene import Camera

__all__ = ["NAMES", "DEFAULT_MAX_EDGE", "CAMERAS", "load", "load_scene", "path"]

NAMES = ("cornell", "room")

#: Subdivision used when no ``--max-edge`` is given (scene units: mm for cornell, m for room).
DEFAULT_MAX_EDGE = {"cornell": 100.0, "room": 0.63}

CAMERAS = {
    "cornell": Camera(position=(278.0, 273.0, -800.0), look_at=(278.0, 273.0, 0.0),
                      up=(0.0, 1.0, 0.0), fov=math.degrees(2.0 * math.atan(0.0125 / 0.035))),
    "room": Camera(position=(0.35, 1.75, 0.35), look_at=(4.2, 0.9, 4.0),
                   up=(0.0, 1.0, 0.0), fov=70.0),
}


def path(name):
    """The OBJ file of a built-in scene."""
    return Path(__file__).resolve().parent / "scenes" / f"{name}.obj"


def load(name, *, max_edge=None, max_triangles=None, contact=True):
    """Load a built-in scene, subdivided to ``max_edge`` (default ``DEFAULT_MAX_EDGE[name]``);
    ``max_triangles``: as :func:`~blockray.host_driver.scene.objload.subdivide`; ``contact``: as
    :func:`load_scene`."""
    if name not in NAMES:
        raise KeyError(name)
    scene = load_obj(path(name), name=name)
    scene.camera = CAMERAS[name]
    scene.source = f"builtin:{name}"
    return _finish(scene, DEFAULT_MAX_EDGE[name] if max_edge is None else max_edge, max_triangles, contact)


def _finish(scene, max_edge, max_triangles, contact):
    """Subdivided, then cut along contact lines (host_driver/scene/contact.py): cut first, a large triangle
    round a small footprint becomes long thin pieces that bisection refines into many more (room:
    3890 patches, smallest angle 0.05 degrees, against 3605 and 0.19 this way). The counts go to
    ``scene.contact`` (the report's ``contact`` key)."""
    info, delta = None, rounding(scene.vertices)       # the file's, not the midpoints'
    if max_edge is not None:
        scene = subdivide(scene, max_edge, max_triangles=max_triangles)
    if contact:
        scene, info = split_contacts(scene, delta)
    scene.contact = info
    return scene


def load_scene(spec, *, max_edge=None, limits=None, contact=True):
    """A built-in scene by name (``cornell``, ``room``) or an OBJ file by path.

    For a built-in scene ``max_edge=None`` means its documented default subdivision
    (see this module); for a file it means no subdivision.
    ``limits``: :class:`LoadLimits` (files read, subdivision size).
    ``contact``: split patches along contact lines and drop the covered pieces
    (host_driver/scene/contact.py; ``--contact off`` turns it off).
    """
    limits = LoadLimits() if limits is None else limits
    if max_edge is not None:
        _check_max_edge(max_edge)
    if spec in NAMES:
        return load(spec, max_edge=max_edge, max_triangles=limits.max_triangles, contact=contact)
    if not os.path.lexists(spec):
        raise SceneError(f"no such scene file or built-in scene (built-ins: "
                         f"{', '.join(NAMES)})", path=spec)
    return _finish(load_obj(spec, limits=limits), max_edge, limits.max_triangles, contact)
