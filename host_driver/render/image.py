"""A picture of a radiosity solution: z-buffer rasteriser, Gouraud shading, tone map, PNG.

- **Projection.** A pinhole :class:`~blockray.host_driver.scene.scene.Camera`: square pixels, vertical
  field of view ``camera.fov``; image x grows along ``forward x up`` (the camera's right),
  image y grows downwards. Pixel (i, j) samples the ray through its centre (i + 0.5, j + 0.5).
  Triangles are clipped against a near plane, so a camera inside the scene is fine.
- **Visibility.** A float z-buffer over 1/z; every triangle is drawn from both sides (no
  back-face culling). Each triangle is rasterised with numpy over its pixel bounding box.
- **Shading.** Radiosity is interpolated to vertices (Gouraud): a corner takes the area-weighted
  mean radiosity of the patches that share its position, belong to the same group and whose
  normal is within ``crease`` degrees of its own, so creases and group boundaries stay sharp.
  Colours are interpolated perspective-correctly across each triangle.
- **Tone map.** Linear exposure that maps the ``white_percentile`` (99th) percentile of the
  luminance (Rec. 709 weights) of visible pixels on non-emitting patches to 1, then clip to
  [0, 1] (emitters and the brightest 1% clip to white) and gamma 2.2. Background is black.
"""

import math

import numpy as np

from blockray.atomic import write_file
from blockray.errors import ParameterError, option

from ..scene.scene import Camera

__all__ = ["default_camera", "project", "vertex_radiosity", "render_image", "save_png", "check_image_size",
           "MAX_PIXELS", "BYTES_PER_PIXEL"]

_LUMINANCE = np.array([0.2126, 0.7152, 0.0722])

#: Peak memory of :func:`render_image` per pixel (tracemalloc, cornell: 135 B at 512 x 512,
#: 130 B at 1024 x 1024; docs/input.md has the command)
BYTES_PER_PIXEL = 135
#: Largest image: 8192 x 8192 pixels, ~9 GB at :data:`BYTES_PER_PIXEL`
MAX_PIXELS = 1 << 26


def check_image_size(width, height):
    """Raise :class:`ParameterError` (naming the ``size``) for an image of more than
    :data:`MAX_PIXELS` pixels: its buffers would not fit in memory."""
    pixels = int(width) * int(height)
    if pixels > MAX_PIXELS:
        raise ParameterError(f"{option('size')}: a {width} x {height} image needs about "
                             f"{pixels * BYTES_PER_PIXEL / 2**30:.3g} GiB of memory; at most {MAX_PIXELS} "
                             f"pixels (8192 x 8192)")


def default_camera(scene, fov=40.0):
    """A camera outside the scene's bounding box, slightly above it, seeing all of it."""
    lo, hi = scene.bbox
    centre = (lo + hi) / 2
    radius = max(float(np.linalg.norm(hi - lo)) / 2, 1e-9)
    direction = np.array([0.0, -0.3, 1.0])
    direction /= np.linalg.norm(direction)
    distance = 1.05 * radius / math.sin(math.radians(fov) / 2)
    return Camera(position=tuple(centre - distance * direction), look_at=tuple(centre),
                  up=(0.0, 1.0, 0.0), fov=fov)


def _basis(camera):
    """Camera position and the (3, 3) rows right, up, forward."""
    position = np.asarray(camera.position, dtype=np.float64)
    forward = np.asarray(camera.look_at, dtype=np.float64) - position
    if not np.linalg.norm(forward) > 0:
        raise ParameterError("camera: look_at equals position")
    forward /= np.linalg.norm(forward)
    right = np.cross(forward, np.asarray(camera.up, dtype=np.float64))
    if not np.linalg.norm(right) > 1e-12:
        raise ParameterError("camera: up is parallel to the viewing direction")
    right /= np.linalg.norm(right)
    up = np.cross(right, forward)
    if not 0 < camera.fov < 180:
        raise ParameterError(f"camera: fov must be between 0 and 180 degrees, not {camera.fov}")
    return position, np.stack([right, up, forward])


def _focal_pixels(camera, height):
    return (height / 2) / math.tan(math.radians(camera.fov) / 2)


def project(points, camera, width, height):
    """Image coordinates (x, y in pixels, continuous) and depth of (..., 3) points."""
    position, basis = _basis(camera)
    c = (np.asarray(points, dtype=np.float64) - position) @ basis.T
    f = _focal_pixels(camera, height)
    return width / 2 + f * c[..., 0] / c[..., 2], height / 2 - f * c[..., 1] / c[..., 2], c[..., 2]


def vertex_radiosity(scene, radiosity, crease=30.0):
    """(N, 3, 3): radiosity at each corner of each patch (see the module docstring)."""
    radiosity = np.asarray(radiosity, dtype=np.float64)
    n = scene.patches
    _, position = np.unique(scene.vertices + 0.0, axis=0, return_inverse=True)
    corner_pos = position.reshape(-1)[scene.triangles].reshape(-1)          # (3N,)
    corner_patch = np.repeat(np.arange(n), 3)
    corner_group = scene.group[corner_patch]
    order = np.lexsort((corner_group, corner_pos))
    key_pos, key_group = corner_pos[order], corner_group[order]
    new = np.ones(len(order), dtype=bool)
    new[1:] = (key_pos[1:] != key_pos[:-1]) | (key_group[1:] != key_group[:-1])
    start = np.flatnonzero(new)
    cluster = np.cumsum(new) - 1                                           # per sorted corner
    size = np.diff(np.append(start, len(order)))[cluster]
    # All ordered pairs (i, j) of sorted corners in the same cluster.
    i = np.repeat(np.arange(len(order)), size)
    offset = np.arange(len(i)) - np.repeat(np.cumsum(size) - size, size)
    j = start[cluster][i] + offset
    pi, pj = corner_patch[order[i]], corner_patch[order[j]]
    same_side = np.sum(scene.normals[pi] * scene.normals[pj], axis=1) >= math.cos(math.radians(crease))
    weight = np.where(same_side, scene.areas[pj], 0.0)
    num = np.zeros((len(order), 3))
    np.add.at(num, i, weight[:, None] * radiosity[pj])
    den = np.bincount(i, weights=weight, minlength=len(order))
    own = radiosity[corner_patch[order]]
    value = np.where(den[:, None] > 0, num / np.where(den > 0, den, 1.0)[:, None], own)
    out = np.empty((3 * n, 3))
    out[order] = value
    return out.reshape(n, 3, 3)


def _clip_near(cam_vertices, colours, near):
    """Clip one triangle (camera space) against z >= near: a list of (3, 3) vertex/colour pairs."""
    poly = list(zip(cam_vertices, colours))
    out = []
    for k in range(len(poly)):
        (p, c), (q, d) = poly[k], poly[(k + 1) % len(poly)]
        if p[2] >= near:
            out.append((p, c))
        if (p[2] >= near) != (q[2] >= near):
            t = (near - p[2]) / (q[2] - p[2])
            out.append((p + t * (q - p), c + t * (d - c)))
    return [(np.array([out[0][0], out[k][0], out[k + 1][0]]),
             np.array([out[0][1], out[k][1], out[k + 1][1]])) for k in range(1, len(out) - 1)]


def render_image(scene, radiosity, *, width=512, height=512, camera=None,
                 white_percentile=99.0, exposure=None, colours=None):
    """Render ``radiosity`` ((N, 3) per patch) on ``scene`` as an (H, W, 3) uint8 sRGB-ish image.

    ``camera`` defaults to ``scene.camera``, else :func:`default_camera`. ``exposure`` (a linear
    factor) overrides the automatic exposure (see the module docstring). ``colours`` (N, 3, 3),
    the patches' corner values, replaces :func:`vertex_radiosity` (hierarchical leaves:
    host_driver/render/conforming.py).
    """
    for value, flag in ((width, "width"), (height, "height")):
        if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < 1:
            raise ParameterError(f"image {flag} must be a positive integer, not {value!r}")
    check_image_size(width, height)
    radiosity = np.asarray(radiosity, dtype=np.float64)
    if radiosity.shape != (scene.patches, 3):
        raise ValueError(f"radiosity must have shape ({scene.patches}, 3), not {radiosity.shape}")
    camera = camera or scene.camera or default_camera(scene)
    position, basis = _basis(camera)
    focal = _focal_pixels(camera, height)
    lo, hi = scene.bbox
    near = 1e-6 * max(float(np.linalg.norm(hi - lo)), float(np.linalg.norm(position - (lo + hi) / 2)))

    cam = (scene.patch_vertices - position) @ basis.T                        # (N, 3, 3)
    colours = vertex_radiosity(scene, radiosity) if colours is None else np.asarray(colours, dtype=np.float64)
    inv_depth = np.zeros((height, width))                                   # 1/z; 0 = nothing
    image = np.zeros((height, width, 3))
    patch_at = np.full((height, width), -1, dtype=np.int64)

    zmin = cam[:, :, 2].min(axis=1)
    zmax = cam[:, :, 2].max(axis=1)
    pieces = [(p, cam[p], colours[p]) for p in np.flatnonzero(zmin >= near)]
    for p in np.flatnonzero((zmin < near) & (zmax >= near)):
        pieces += [(p, v, c) for v, c in _clip_near(cam[p], colours[p], near)]

    for p, v, c in pieces:
        z = v[:, 2]
        sx = width / 2 + focal * v[:, 0] / z
        sy = height / 2 - focal * v[:, 1] / z
        x0 = max(math.ceil(sx.min() - 0.5), 0)
        x1 = min(math.floor(sx.max() - 0.5), width - 1)
        y0 = max(math.ceil(sy.min() - 0.5), 0)
        y1 = min(math.floor(sy.max() - 0.5), height - 1)
        if x0 > x1 or y0 > y1:
            continue
        area = (sx[1] - sx[0]) * (sy[2] - sy[0]) - (sy[1] - sy[0]) * (sx[2] - sx[0])
        if area == 0:
            continue
        px = np.arange(x0, x1 + 1) + 0.5
        py = (np.arange(y0, y1 + 1) + 0.5)[:, None]
        # Barycentric weights of the pixel centres (edge functions / area).
        b0 = ((sx[2] - sx[1]) * (py - sy[1]) - (sy[2] - sy[1]) * (px - sx[1])) / area
        b1 = ((sx[0] - sx[2]) * (py - sy[2]) - (sy[0] - sy[2]) * (px - sx[2])) / area
        b2 = 1.0 - b0 - b1
        inside = (b0 >= -1e-9) & (b1 >= -1e-9) & (b2 >= -1e-9)
        if not inside.any():
            continue
        w = np.stack([b0, b1, b2], axis=-1)[inside] / z                      # (M, 3)
        iz = w.sum(axis=1)
        rows, cols = np.nonzero(inside)
        rows += y0
        cols += x0
        closer = iz > inv_depth[rows, cols]
        if not closer.any():
            continue
        rows, cols, w, iz = rows[closer], cols[closer], w[closer], iz[closer]
        inv_depth[rows, cols] = iz
        image[rows, cols] = (w @ c) / iz[:, None]
        patch_at[rows, cols] = p

    visible = patch_at >= 0
    if exposure is None:
        luminance = image @ _LUMINANCE
        emitter = np.zeros_like(visible)
        emitter[visible] = scene.emission[patch_at[visible]].max(axis=1) > 0
        sample = luminance[visible & ~emitter]
        if sample.size == 0:
            sample = luminance[visible]
        white = float(np.percentile(sample, white_percentile)) if sample.size else 0.0
        exposure = 1.0 / white if white > 0 else 1.0
    out = np.clip(image * exposure, 0.0, 1.0) ** (1 / 2.2)
    return np.round(out * 255).astype(np.uint8)


def save_png(path, image, outputs=None):
    """Write an (H, W, 3) uint8 image as PNG (``--image``), atomically (:mod:`blockray.atomic`):
    alone, or staged in the batch ``outputs``. A failed write raises ResourceError naming the file."""
    from PIL import Image
    picture = Image.fromarray(np.ascontiguousarray(image, dtype=np.uint8), "RGB")
    write_file(path, "--image", lambda f: picture.save(f, format="PNG"), binary=True, outputs=outputs)
