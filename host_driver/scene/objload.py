"""Wavefront OBJ + MTL loader, subdivision, and scene lookup by name or path.

What is read:

- OBJ: ``v x y z [w]`` (``w`` and the 6-number ``v x y z r g b`` colour extension are accepted
  and ignored), ``f`` with ``v``, ``v/vt``, ``v//vn`` or ``v/vt/vn`` corners and positive or
  negative (relative) indices, ``o``/``g`` (the group of the triangles that follow), ``mtllib``
  and ``usemtl``. Texture coordinates and vertex normals are checked for range and otherwise
  ignored: the patch normal is the right-handed normal of the corner order. Lines, points,
  smoothing groups and other display statements are ignored; free-form geometry and any unknown
  statement is an error.
- MTL: ``newmtl``, ``Kd`` (RGB reflectance, each in [0, 1)) and ``Ke`` (RGB emission, >= 0).
  Other statements (``Ka``, ``Ks``, ``map_*``, ...) are ignored. A material without ``Kd``, and
  faces before any ``usemtl``, get :data:`DEFAULT_REFLECTANCE`; without ``Ke`` emission is 0.

Polygons are triangulated: a fan for convex polygons (a non-planar quad such as the Cornell red
wall becomes two triangles), ear clipping in the polygon's best-fit plane otherwise. Every
triangle is one patch. Exactly coincident vertex positions are merged, so faces that repeat a
vertex instead of sharing its index still share the edge (this keeps :func:`subdivide`
crack-free across them). Unused vertices are dropped.

Bad input raises :class:`~blockray.errors.SceneError` naming the file and line. Zero-area
triangles are dropped with one :class:`SceneWarning` (a :mod:`warnings` warning) that counts them;
the CLI prints it.

Untrusted files (downloaded models, a service rendering uploads) are read under
:class:`LoadLimits`:

- Only regular files are read (a FIFO or ``/dev/zero`` is refused before it is read), at most
  ``max_file_bytes`` each.
- ``mtllib`` files must lie inside the OBJ file's folder tree (after following symbolic links)
  unless ``allow_mtl_outside``; a path outside is refused without looking at it, so the error does
  not say whether it exists.
- An error message quotes at most the offending token, cut to :data:`TOKEN_CHARS` characters and
  with control characters escaped, never a whole line of a file.
- Text is UTF-8 (a byte-order mark is skipped); lines end at line feeds; a trailing backslash joins
  the next line (also on the last line); fields are separated by ASCII blanks. Bytes that are not
  UTF-8 are kept as they are (``surrogateescape``): material names match byte for byte, so an OBJ
  and an MTL naming a material with different invalid bytes do not match (they used to both read
  as U+FFFD); group names show each such byte as U+FFFD.
- Numbers are the OBJ format's: ``[+-]digits[.digits][(e|E)[+-]digits]`` in ASCII digits (no
  ``inf``, ``nan``, ``1_0`` or other scripts' digits); indices are ASCII integers.
- A vertex coordinate beyond :data:`~blockray.host_driver.scene.scene.COORDINATE_LIMIT` in magnitude,
  and a scene smaller than :data:`~blockray.host_driver.scene.scene.MIN_EXTENT`, are refused (see
  :func:`~blockray.host_driver.scene.scene.check_range`).
- A material defined twice (``newmtl`` with a name already defined) is an error.
- :func:`subdivide` refuses, before it starts, a ``max_edge`` whose subdivision would give more
  than ``max_triangles`` triangles (a lower bound of the count is computed first).
"""

import math
import os
import re
import stat
import warnings
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from blockray.errors import ParameterError, SceneError, option, printable

from .scene import COORDINATE_LIMIT, Scene, check_range

__all__ = ["DEFAULT_REFLECTANCE", "LoadLimits", "SceneWarning", "TOKEN_CHARS", "load_obj",
           "subdivide", "subdivision_lower_bound"]

#: At most this many characters of a token are quoted in an error message.
TOKEN_CHARS = 24

# The OBJ format's numbers (ASCII only: Python's float() also takes "1_0", "inf" and other
# scripts' digits) and indices.
_FLOAT = re.compile(r"[+-]?(?:[0-9]+\.?[0-9]*|\.[0-9]+)(?:[eE][+-]?[0-9]+)?")
_INT = re.compile(r"[+-]?[0-9]+")
_BLANKS = re.compile(r"[ \t\r\f\v]+")


@dataclass(frozen=True)
class LoadLimits:
    """What the loader may read (see the module docstring). The CLI sets these from
    ``--allow-mtl-outside``, ``--max-file-mb`` and ``--max-patches``."""
    allow_mtl_outside: bool = False
    max_file_bytes: int = 256 << 20         # a 256 MiB OBJ holds millions of triangles
    max_triangles: int = 1_000_000          # subdivision output; cornell to 110 k takes ~10 s (docs/input.md)


def _token(text):
    """A token of a file as an error message may quote it: cut short, escapes escaped."""
    return "'" + printable(text, TOKEN_CHARS) + "'"

#: Reflectance of a material without ``Kd`` and of faces before any ``usemtl`` (the usual
#: exporter default, e.g. Blender's).
DEFAULT_REFLECTANCE = (0.8, 0.8, 0.8)

#: A triangle is degenerate when twice its area is at most this fraction of its longest edge
#: squared (i.e. its height is below ~1e-12 of its longest edge).
_DEGENERATE = 1e-12

_OBJ_IGNORED = {
    "vp", "s", "l", "p", "mg", "usemap", "maplib", "shadow_obj", "trace_obj", "lod", "bevel",
    "c_interp", "d_interp",
}
_OBJ_FREEFORM = {"cstype", "deg", "bmat", "step", "curv", "curv2", "surf", "parm", "trim",
                 "hole", "scrv", "sp", "end", "con"}


class SceneWarning(UserWarning):
    """A scene was loaded, but something in it was dropped or repaired."""


class _Material:
    __slots__ = ("name", "path", "line", "reflectance", "emission")

    def __init__(self, name, path, line):
        self.name, self.path, self.line = name, path, line
        self.reflectance = DEFAULT_REFLECTANCE
        self.emission = (0.0, 0.0, 0.0)


def _numbers(fields, counts, path, lineno, what):
    if len(fields) not in counts:
        expected = " or ".join(str(c) for c in counts)
        raise SceneError(f"'{what}' needs {expected} numbers, got {len(fields)}",
                         path=path, line=lineno)
    values = []
    for f in fields:
        if not _FLOAT.fullmatch(f):
            raise SceneError(f"'{what}' has a value that is not a number: {_token(f)}",
                             path=path, line=lineno)
        values.append(float(f))
    return values


def _read_text(path, limits, error_path=None, error_line=None, what="file"):
    """The text of ``path``: a regular file of at most ``limits.max_file_bytes``, UTF-8 with an
    optional byte-order mark. Errors name ``error_path`` (default ``path``) and ``error_line``."""
    where = {"path": error_path if error_path is not None else path, "line": error_line}
    try:
        # stat before open: opening a FIFO blocks, opening a device may do things
        st = os.stat(path)
        if not stat.S_ISREG(st.st_mode):
            raise SceneError(f"{what} is not a regular file", **where)
        fd = os.open(path, os.O_RDONLY | getattr(os, "O_NONBLOCK", 0) | getattr(os, "O_CLOEXEC", 0))
        with os.fdopen(fd, "rb") as f:
            if not stat.S_ISREG(os.fstat(f.fileno()).st_mode):     # replaced since the stat
                raise SceneError(f"{what} is not a regular file", **where)
            data = f.read(limits.max_file_bytes + 1)
    except FileNotFoundError:
        raise SceneError(f"{what} not found", **where) from None
    except OSError as e:
        raise SceneError(f"cannot read {what}: {e.strerror or type(e).__name__}", **where) from None
    except ValueError:                      # a NUL character in the name
        raise SceneError(f"{what} is not a file name", **where) from None
    if len(data) > limits.max_file_bytes:
        raise SceneError(f"{what} is larger than {limits.max_file_bytes / 2**20:.3g} MiB "
                         f"(raise the limit with {option('max_file_bytes')})", **where)
    return data.decode("utf-8-sig", errors="surrogateescape")


def _shown(text):
    """``text`` with the bytes that were not UTF-8 (kept by :func:`_read_text`) as U+FFFD."""
    return text.encode("utf-8", errors="surrogateescape").decode("utf-8", errors="replace")


def _not_utf8(name):
    """A hint for a message about ``name`` if it holds bytes that are not UTF-8."""
    return " (not valid UTF-8; material names are compared byte for byte)" if _shown(name) != name else ""


def _read_lines(path, limits, error_path=None, error_line=None, what="file"):
    """Yield (line number, keyword, fields) of a text file, joining backslash continuations."""
    text = _read_text(path, limits, error_path, error_line, what)
    pending, start = "", None
    for lineno, raw in enumerate(text.split("\n"), 1):
        line = raw.split("#", 1)[0].rstrip(" \t\r\f\v")
        if line.endswith("\\"):
            if start is None:
                start = lineno
            pending += line[:-1] + " "
            continue
        line = pending + line
        first, pending, start = (start or lineno), "", None
        fields = [f for f in _BLANKS.split(line) if f]
        if fields:
            yield first, fields[0], fields[1:]
    if pending:                  # a continuation on the last line: the statement ends there
        fields = [f for f in _BLANKS.split(pending) if f]
        if fields:
            yield start, fields[0], fields[1:]


def _load_mtl(path, materials, limits, obj_path, obj_line, shown):
    """Read materials from ``path`` into ``materials`` (name -> _Material). ``shown``: the
    ``mtllib`` token, quoted in errors about the file as a whole (at the OBJ's line)."""
    current = None
    for lineno, key, fields in _read_lines(path, limits, obj_path, obj_line,
                                           what=f"material library {_token(shown)}"):
        if key == "newmtl":
            if not fields:
                raise SceneError("'newmtl' needs a name", path=path, line=lineno)
            name = " ".join(fields)
            if name in materials:
                first = materials[name]
                raise SceneError(f"material {_token(name)} is defined twice (first at "
                                 f"{printable(first.path, 200)}:{first.line})", path=path, line=lineno)
            current = materials[name] = _Material(name, path, lineno)
        elif key in ("Kd", "Ke"):
            if current is None:
                raise SceneError(f"'{key}' before any 'newmtl'", path=path, line=lineno)
            if fields and fields[0] in ("spectral", "xyz"):
                raise SceneError(f"'{key} {fields[0]}' is not supported; give RGB values",
                                 path=path, line=lineno)
            values = _numbers(fields, (1, 3), path, lineno, key)
            if len(values) == 1:
                values = values * 3
            if key == "Kd":
                bad = [f for f, c in zip(fields * 3, values) if not 0.0 <= c < 1.0]   # also NaN
                if bad:
                    raise SceneError(f"material {_token(current.name)}: reflectance Kd {_token(bad[0])} "
                                     f"is outside [0, 1)", path=path, line=lineno)
                current.reflectance = tuple(values)
            else:
                bad = [f for f, c in zip(fields * 3, values) if not 0.0 <= c < math.inf]
                if bad:
                    raise SceneError(f"material {_token(current.name)}: emission Ke {_token(bad[0])} "
                                     f"must be finite and >= 0", path=path, line=lineno)
                current.emission = tuple(values)


def _may_read(folder, mtl, limits):
    """Whether ``mtllib`` may read ``mtl`` (relative to the OBJ's ``folder``) under ``limits``."""
    return limits.allow_mtl_outside or _inside(folder, folder / mtl)


def _inside(folder, target):
    """Whether ``target`` is in the folder tree of ``folder`` once symbolic links are followed."""
    if "\0" in str(target):
        return False
    root = os.path.realpath(folder)
    return os.path.commonpath([root, os.path.realpath(target)]) == root


#: Concave polygons with more corners are refused: ear clipping takes O(n**3) steps here.
MAX_CONCAVE_CORNERS = 200


def _triangulate(poly, p):
    """Split a polygon (list of vertex indices, ``p`` their (n, 3) positions) into triangles
    (list of index triples). Raises ValueError for a concave polygon of too many corners."""
    n = len(poly)
    if n == 3:
        return [tuple(poly)]
    # Newell normal: robust best-fit plane normal of a (possibly non-planar) polygon.
    q = np.roll(p, -1, axis=0)
    normal = np.array([
        np.sum((p[:, 1] - q[:, 1]) * (p[:, 2] + q[:, 2])),
        np.sum((p[:, 2] - q[:, 2]) * (p[:, 0] + q[:, 0])),
        np.sum((p[:, 0] - q[:, 0]) * (p[:, 1] + q[:, 1])),
    ])
    axis = int(np.argmax(np.abs(normal)))
    u, v = [(1, 2), (2, 0), (0, 1)][axis]
    xy = p[:, [u, v]].copy()
    if normal[axis] < 0:
        xy[:, 1] = -xy[:, 1]
    # xy is now counter-clockwise (positive area) when seen along the normal.

    def turn(a, b, c):
        return (xy[b, 0] - xy[a, 0]) * (xy[c, 1] - xy[a, 1]) - \
               (xy[b, 1] - xy[a, 1]) * (xy[c, 0] - xy[a, 0])

    if all(turn(i, (i + 1) % n, (i + 2) % n) >= 0 for i in range(n)):
        return [(poly[0], poly[i], poly[i + 1]) for i in range(1, n - 1)]

    # Ear clipping for a concave polygon.
    if n > MAX_CONCAVE_CORNERS:
        raise ValueError(f"a concave polygon of {n} corners (at most {MAX_CONCAVE_CORNERS}); "
                         "split it into smaller faces")
    remaining = list(range(n))
    triangles = []
    while len(remaining) > 3:
        m = len(remaining)
        for k in range(m):
            a, b, c = remaining[k - 1], remaining[k], remaining[(k + 1) % m]
            if turn(a, b, c) <= 0:
                continue
            if any(turn(a, b, d) >= 0 and turn(b, c, d) >= 0 and turn(c, a, d) >= 0
                   for d in remaining if d not in (a, b, c)):
                continue
            triangles.append((poly[a], poly[b], poly[c]))
            del remaining[k]
            break
        else:   # self-intersecting or degenerate: fall back to a fan of what is left
            triangles += [(poly[remaining[0]], poly[remaining[i]], poly[remaining[i + 1]])
                          for i in range(1, len(remaining) - 1)]
            return triangles
    triangles.append(tuple(poly[i] for i in remaining))
    return triangles


class _ObjReader:
    """One OBJ file's statements as they are read: vertices, faces (index triples) with their group
    and material, and the materials of the libraries read so far. Errors name the file and line."""

    def __init__(self, path, limits):
        self.path, self.folder, self.limits = path, path.parent, limits
        self.vertices, self.texcoords, self.normals = [], 0, 0
        self.faces, self.face_group, self.face_mat = [], [], []
        self.group_names, self.group_ids = [], {}
        self.materials = {}
        self.libraries = set()                     # real paths of the MTL files read
        self.usemtl_lines = {}                     # material name -> first OBJ line using it
        self.group, self.material = None, None

    def statement(self, lineno, key, fields):
        handler = self._HANDLERS.get(key)
        if handler is not None:
            handler(self, lineno, fields)
        elif key in _OBJ_FREEFORM:
            raise SceneError(f"free-form geometry ('{key}') is not supported", path=self.path, line=lineno)
        elif key not in _OBJ_IGNORED:
            raise SceneError(f"unknown statement {_token(key)}", path=self.path, line=lineno)

    def _vertex(self, lineno, fields):
        values = _numbers(fields, (3, 4, 6), self.path, lineno, "v")
        for f, c in zip(fields, values[:3]):
            if not abs(c) <= COORDINATE_LIMIT:
                raise SceneError(f"vertex coordinate {_token(f)} is beyond +-{COORDINATE_LIMIT:g}, "
                                 f"the range the boards compute in (scale the scene down)",
                                 path=self.path, line=lineno)
        self.vertices.append(values[:3])

    def _texcoord(self, lineno, fields):
        _numbers(fields, (1, 2, 3), self.path, lineno, "vt")
        self.texcoords += 1

    def _normal(self, lineno, fields):
        _numbers(fields, (3,), self.path, lineno, "vn")
        self.normals += 1

    def _index(self, token, count, lineno, kind):
        if not _INT.fullmatch(token):
            raise SceneError(f"bad {kind} index {_token(token)} in 'f'", path=self.path, line=lineno)
        i = int(token)
        if i > 0 and i <= count:
            return i - 1
        if i < 0 and -i <= count:
            return count + i
        raise SceneError(f"{kind} index {i} out of range (there are {count} {kind}s so far)",
                         path=self.path, line=lineno)

    def _face(self, lineno, fields):
        if len(fields) < 3:
            raise SceneError(f"'f' needs at least 3 corners, got {len(fields)}", path=self.path, line=lineno)
        poly = []
        for corner in fields:
            parts = corner.split("/")
            if len(parts) > 3 or not parts[0]:
                raise SceneError(f"bad face corner {_token(corner)}", path=self.path, line=lineno)
            poly.append(self._index(parts[0], len(self.vertices), lineno, "vertex"))
            if len(parts) > 1 and parts[1]:
                self._index(parts[1], self.texcoords, lineno, "texture coordinate")
            if len(parts) > 2 and parts[2]:
                self._index(parts[2], self.normals, lineno, "normal")
        try:
            triangles = _triangulate(poly, np.array([self.vertices[i] for i in poly], dtype=np.float64))
        except ValueError as e:
            raise SceneError(str(e), path=self.path, line=lineno) from None
        g = self._group_id(self.group if self.group is not None else "default")
        for tri in triangles:
            self.faces.append(tri)
            self.face_group.append(g)
            self.face_mat.append(self.material)

    def _group_id(self, gname):
        if gname not in self.group_ids:
            self.group_ids[gname] = len(self.group_names)
            self.group_names.append(_shown(gname))
        return self.group_ids[gname]

    def _set_group(self, lineno, fields):
        self.group = " ".join(fields) if fields else "default"

    def _mtllib(self, lineno, fields):
        path, folder, limits = self.path, self.folder, self.limits
        if not fields:
            raise SceneError("'mtllib' needs a file name", path=path, line=lineno)
        # one file name with blanks, else several names; a path outside the folder tree is
        # not even looked at unless allowed (whether it exists is not revealed)
        whole = " ".join(fields)
        names = fields
        if len(fields) > 1 and _may_read(folder, whole, limits) and (folder / whole).is_file():
            names = [whole]
        for mtl in names:
            if "\0" in mtl:           # no file name holds one; os.path would raise
                raise SceneError(f"material library {_token(mtl)} is not a file name", path=path,
                                 line=lineno)
            if not _may_read(folder, mtl, limits):
                raise SceneError(f"material library {_token(mtl)} is outside the scene's folder "
                                 f"(allow it with {option('allow_mtl_outside')})", path=path, line=lineno)
            real = os.path.realpath(folder / mtl)
            if real not in self.libraries:          # a library named again is not read twice
                self.libraries.add(real)
                _load_mtl(folder / mtl, self.materials, limits, path, lineno, mtl)

    def _usemtl(self, lineno, fields):
        if not fields:
            raise SceneError("'usemtl' needs a material name", path=self.path, line=lineno)
        self.material = " ".join(fields)
        self.usemtl_lines.setdefault(self.material, lineno)

    _HANDLERS = {"v": _vertex, "vt": _texcoord, "vn": _normal, "f": _face, "o": _set_group,
                 "g": _set_group, "mtllib": _mtllib, "usemtl": _usemtl}

    def patches(self):
        """(coordinates, triangles, reflectance, emission, group) of the faces read: every
        material used defined, coincident positions merged, unused vertices and zero-area
        triangles dropped (with a :class:`SceneWarning` to load_obj's caller)."""
        path = self.path
        for mname, lineno in self.usemtl_lines.items():
            if mname not in self.materials:
                raise SceneError(f"unknown material {_token(mname)}{_not_utf8(mname)}", path=path, line=lineno)
        if not self.faces:
            raise SceneError("the scene has no triangles", path=path)
        coords, tris = _weld(self.vertices, self.faces)
        refl = np.array([self.materials[m].reflectance if m is not None else DEFAULT_REFLECTANCE
                         for m in self.face_mat], dtype=np.float64)
        emis = np.array([self.materials[m].emission if m is not None else (0.0, 0.0, 0.0)
                         for m in self.face_mat], dtype=np.float64)
        groups = np.array(self.face_group, dtype=np.int64)

        keep = ~_degenerate(coords[tris])
        dropped = int(np.count_nonzero(~keep))
        if dropped:
            warnings.warn(f"{printable(path, 200)}: dropped {dropped} zero-area triangle{'s' if dropped > 1 else ''}",
                          SceneWarning, stacklevel=3)
            if not keep.any():
                raise SceneError("the scene has no triangles of non-zero area", path=path)
            tris, refl, emis, groups = tris[keep], refl[keep], emis[keep], groups[keep]
            used, tris = np.unique(tris, return_inverse=True)
            tris = tris.reshape(-1, 3)
            coords = coords[used]
        return coords, tris, refl, emis, groups


def _weld(vertices, faces):
    """(coordinates, triangles): exactly coincident positions merged, unused vertices dropped."""
    coords = np.array(vertices, dtype=np.float64) + 0.0   # + 0.0 turns -0.0 into 0.0 for unique
    tris = np.array(faces, dtype=np.int64)
    unique, inverse = np.unique(coords, axis=0, return_inverse=True)
    tris = inverse.reshape(-1)[tris]
    used, tris = np.unique(tris, return_inverse=True)
    return unique[used], tris.reshape(-1, 3)


def load_obj(path, *, max_edge=None, name=None, limits=None):
    """Load a Wavefront OBJ file (and its MTL files) as a :class:`Scene`.

    Parameters
    ----------
    path : str or Path
        The OBJ file. ``mtllib`` paths are relative to its folder.
    max_edge : float, optional
        If given, :func:`subdivide` the scene so no edge is longer than this.
    name : str, optional
        Scene name; the file's stem by default.
    limits : LoadLimits, optional
        What may be read (default :class:`LoadLimits()`: MTL files inside the OBJ's folder tree,
        256 MiB per file, at most a million triangles after subdivision).

    Raises
    ------
    SceneError
        Unreadable, non-regular, too large or malformed file, index out of range, coordinate
        out of range, reflectance outside [0, 1), negative emission, unknown or twice-defined
        material, missing MTL file or one outside the folder tree, no triangles. The message
        names the file and line.
    ParameterError
        ``max_edge`` is not a positive number, or gives too many triangles.

    Warns
    -----
    SceneWarning
        Zero-area triangles were dropped (the message counts them).
    """
    path = Path(path)
    limits = LoadLimits() if limits is None else limits
    obj = _ObjReader(path, limits)
    for lineno, key, fields in _read_lines(path, limits, what="scene file"):
        obj.statement(lineno, key, fields)
    coords, tris, refl, emis, groups = obj.patches()
    scene = Scene(name=name if name is not None else path.stem, vertices=coords, triangles=tris,
                  reflectance=refl, emission=emis, group=groups, group_names=obj.group_names,
                  source=str(path))
    check_range(scene.vertices, path=path)
    if max_edge is not None:
        scene = subdivide(scene, max_edge, max_triangles=limits.max_triangles)
    return scene


def _degenerate(tri_vertices):
    """(N,) bool: triangles whose area is zero relative to their size (see ``_DEGENERATE``)."""
    v = tri_vertices
    cross = np.linalg.norm(np.cross(v[:, 1] - v[:, 0], v[:, 2] - v[:, 0]), axis=1)
    edges = np.stack([v[:, 1] - v[:, 0], v[:, 2] - v[:, 1], v[:, 0] - v[:, 2]], axis=1)
    longest2 = np.max(np.sum(edges * edges, axis=2), axis=1)
    return cross <= _DEGENERATE * longest2


def _check_max_edge(max_edge):
    try:
        value = float(max_edge)
    except (TypeError, ValueError):
        raise ParameterError(f"{option('max_edge')} must be a positive number, not {max_edge!r}") from None
    if not value > 0:                      # also rejects NaN
        raise ParameterError(f"{option('max_edge')} must be a positive number, not {max_edge!r}")
    return value


def subdivision_lower_bound(scene, max_edge):
    """A lower bound of the triangle count :func:`subdivide` gives (float; inf if huge).

    A child has every edge <= ``max_edge`` = L, so its area is at most the equilateral
    triangle's, sqrt(3)/4 L**2, and an edge of length l is cut into at least ceil(l / L) pieces,
    each on a different child: a triangle of area A becomes at least
    max(1, A / (sqrt(3)/4 L**2), ceil(l_max / L)) triangles.
    """
    limit = _check_max_edge(max_edge)
    v = scene.patch_vertices
    edges = np.stack([v[:, 1] - v[:, 0], v[:, 2] - v[:, 1], v[:, 0] - v[:, 2]], axis=1)
    longest = np.max(np.linalg.norm(edges, axis=2), axis=1)
    with np.errstate(over="ignore", divide="ignore", invalid="ignore"):
        by_area = scene.areas / limit / limit / (math.sqrt(3) / 4)   # not limit**2: it may underflow
        by_edge = np.ceil(longest / limit)
        per = np.maximum(1.0, np.maximum(by_area, by_edge))
        return float(np.sum(np.where(np.isnan(per), math.inf, per)))


def _too_many(max_edge, count, max_triangles, at_least=True):
    if not math.isfinite(count):
        shown = "more than 1e308"
    else:
        shown = f"at least {count:.3g}" if at_least else f"{count}"
    return ParameterError(f"{option('max_edge')} {max_edge:g} would subdivide the scene into {shown} triangles, more than the limit of {max_triangles} (use a larger "
                          f"{option('max_edge')}, or raise the limit with {option('max_triangles')})")


def subdivide(scene, max_edge, *, max_triangles=None):
    """Split the triangles of ``scene`` until no edge is longer than ``max_edge``.

    Conforming longest-edge bisection (Rivara): each pass marks the longest edge of every
    triangle that is too long, then propagates marks so every triangle with a marked edge also
    has its longest edge marked; a marked triangle is bisected at the midpoint of its longest
    edge and each half is bisected again at its other marked edge. Midpoints are shared per edge
    (vertex-index pair), so triangles sharing an edge split it at the same vertex: no cracks and
    no T-junctions. Angles stay bounded away from 0. Children keep the group, reflectance and
    emission of their parent and its orientation (normal direction). Ties between equally long
    edges are broken by vertex indices, so the choice depends on the edge only.

    ``max_triangles`` (default ``LoadLimits().max_triangles``): a ``max_edge`` whose
    :func:`subdivision_lower_bound` exceeds it is refused before any work, and the subdivision
    stops with the same error if it passes it.

    Raises
    ------
    ParameterError
        ``max_edge`` is not a positive number, or gives more than ``max_triangles`` triangles
        (names ``--max-edge`` and the count).
    """
    limit = _check_max_edge(max_edge)
    max_triangles = LoadLimits().max_triangles if max_triangles is None else max_triangles
    estimate = subdivision_lower_bound(scene, limit)
    if estimate > max_triangles:
        raise _too_many(limit, estimate, max_triangles)
    limit2 = limit * limit
    verts = [tuple(v) for v in scene.vertices]
    tris = [tuple(int(i) for i in t) for t in scene.triangles]
    parent = list(range(len(tris)))
    midpoint = {}

    def length2(a, b):
        pa, pb = verts[a], verts[b]
        return (pa[0] - pb[0]) ** 2 + (pa[1] - pb[1]) ** 2 + (pa[2] - pb[2]) ** 2

    def key(a, b):
        return (a, b) if a < b else (b, a)

    def longest(t):
        """Index k of the longest edge (t[k], t[k+1]) with a deterministic tie-break."""
        return max(range(3), key=lambda k: (length2(t[k], t[(k + 1) % 3]),
                                            key(t[k], t[(k + 1) % 3])))

    def mid(a, b):
        k = key(a, b)
        m = midpoint.get(k)
        if m is None:
            pa, pb = verts[a], verts[b]
            verts.append(((pa[0] + pb[0]) * 0.5, (pa[1] + pb[1]) * 0.5, (pa[2] + pb[2]) * 0.5))
            m = midpoint[k] = len(verts) - 1
        return m

    while True:
        longest_edge = [longest(t) for t in tris]
        marked = set()
        for t, k in zip(tris, longest_edge):
            a, b = t[k], t[(k + 1) % 3]
            if length2(a, b) > limit2:
                marked.add(key(a, b))
        if not marked:
            break
        # Propagate: a triangle with any marked edge must have its longest edge marked.
        edge_tris = {}
        for i, t in enumerate(tris):
            for k in range(3):
                edge_tris.setdefault(key(t[k], t[(k + 1) % 3]), []).append(i)
        todo = [i for e in marked for i in edge_tris[e]]
        while todo:
            i = todo.pop()
            t, k = tris[i], longest_edge[i]
            e = key(t[k], t[(k + 1) % 3])
            if e not in marked:
                marked.add(e)
                todo.extend(edge_tris[e])
        new_tris, new_parent = [], []
        for t, k, p in zip(tris, longest_edge, parent):
            # Rotate so the longest edge is (a, b), c opposite.
            a, b, c = t[k], t[(k + 1) % 3], t[(k + 2) % 3]
            if key(a, b) not in marked:
                new_tris.append(t)
                new_parent.append(p)
                continue
            m = mid(a, b)
            # halves (a, m, c) and (m, b, c) keep the orientation of (a, b, c)
            for half, (x, y) in (((a, m, c), (c, a)), ((m, b, c), (b, c))):
                if key(x, y) in marked:    # the half's other original edge is marked too
                    n = mid(x, y)
                    if x == c:      # half (a, m, c), edge (c, a): split into (a, m, n), (m, c, n)
                        new_tris += [(a, m, n), (m, c, n)]
                    else:           # half (m, b, c), edge (b, c): split into (m, b, n), (m, n, c)
                        new_tris += [(m, b, n), (m, n, c)]
                    new_parent += [p, p]
                else:
                    new_tris.append(half)
                    new_parent.append(p)
        tris, parent = new_tris, new_parent
        if len(tris) > max_triangles:
            raise _too_many(limit, len(tris), max_triangles, at_least=False)

    parent = np.array(parent, dtype=np.int64)
    return Scene(name=scene.name, vertices=np.array(verts, dtype=np.float64),
                 triangles=np.array(tris, dtype=np.int64).reshape(-1, 3),
                 reflectance=scene.reflectance[parent].copy(),
                 emission=scene.emission[parent].copy(), group=scene.group[parent].copy(),
                 group_names=list(scene.group_names), camera=scene.camera, source=scene.source)
