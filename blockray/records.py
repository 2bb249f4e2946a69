"""Packed records shared by gateware, models, cocotb and the host.

Each record is one :mod:`amaranth.lib.data` layout. The RTL uses it as a stream payload; the
host, the bit-exact model and cocotb pack and unpack with :func:`pack` / :func:`unpack`, which
read field offsets from the same layout object (no hand-written shifts anywhere).

``point_layout(B)``  a sample point or vertex: x, y, z unsigned B bits
``patch_layout(B)``  a patch record as stored in board memory: the three vertices and the
                     host-precomputed normal n = (V1 - V0) x (V2 - V0), signed 2B+2 bits each
"""

import weakref

import numpy as np
from amaranth.hdl import unsigned, signed, Shape
from amaranth.lib import data

from .params import Widths

__all__ = ["point_layout", "patch_layout", "leaves", "pack", "unpack", "pack_array", "pack_bytes", "unpack_array"]


def point_layout(bits):
    return data.StructLayout({"x": unsigned(bits), "y": unsigned(bits), "z": unsigned(bits)})


def vector_layout(width):
    """A signed 3-vector (x, y, z), e.g. a normal or a row term."""
    return data.StructLayout({"x": signed(width), "y": signed(width), "z": signed(width)})


def patch_layout(bits):
    w = Widths(bits)
    point = point_layout(bits)
    return data.StructLayout({
        "v0": point, "v1": point, "v2": point,
        "normal": vector_layout(w.cross),
    })


def leaves(layout, prefix=(), offset=0):
    """Yield ``(path, offset, Shape)`` for every leaf field of ``layout``, in bit order."""
    if isinstance(layout, data.Layout):
        for key, field in layout:
            yield from leaves(field.shape, prefix + (key,), offset + field.offset)
    else:
        yield prefix, offset, Shape.cast(layout)


def _value_leaves(layout, value, prefix=(), offset=0):
    """Like :func:`leaves`, but guided by ``value``: a union packs only the member given."""
    if isinstance(layout, data.UnionLayout):
        given = [key for key, _ in layout if key in value]
        if len(given) > 1:
            raise ValueError(f"union {'.'.join(map(str, prefix)) or 'value'} given more than one "
                             f"member: {', '.join(given)}")
        for key in given:
            yield from _value_leaves(layout[key].shape, value[key], prefix + (key,), offset)
    elif isinstance(layout, data.Layout):
        for key, field in layout:
            yield from _value_leaves(field.shape, value[key], prefix + (key,), offset + field.offset)
    else:
        yield prefix, offset, Shape.cast(layout), value


def pack(layout, value):
    """Pack a nested dict/sequence ``value`` into an int, using the layout's own offsets.

    A :class:`~amaranth.lib.data.UnionLayout` takes a dict with at most one member (none: zero
    bits), as ``layout.const`` does. Equivalent to ``layout.const(value).as_bits()`` (tests
    check that) but much faster.
    """
    bits = 0
    for path, offset, shape, v in _value_leaves(layout, value):
        v = int(v)
        lo, hi = (-(1 << (shape.width - 1)), 1 << (shape.width - 1)) if shape.signed else (0, 1 << shape.width)
        if not lo <= v < hi:
            raise ValueError(f"field {'.'.join(map(str, path))} = {v} does not fit {shape!r}")
        bits |= (v & ((1 << shape.width) - 1)) << offset
    return bits


_fields = {}


def _leaf_fields(layout):
    """:func:`leaves` of ``layout`` as ``(path, offset, width, signed)``, computed once per layout
    object while it lives: walking a layout through Amaranth costs far more than the unpacking.
    Keyed by identity (comparing layouts by value walks them too)."""
    key = id(layout)
    hit = _fields.get(key)
    if hit is not None and hit[0]() is layout:
        return hit[1]
    fields = tuple((path, offset, shape.width, shape.signed) for path, offset, shape in leaves(layout))
    _fields[key] = (weakref.ref(layout, lambda _, key=key: _fields.pop(key, None)), fields)
    return fields


def unpack(layout, bits):
    """Unpack an int into a nested dict (lists for array layouts) of Python ints.

    Every member of a union is unpacked (each is a view of the same bits, as in Amaranth).
    """
    out = {}
    bits = int(bits)
    for path, offset, width, signed in _leaf_fields(layout):
        v = (bits >> offset) & ((1 << width) - 1)
        if signed and v >> (width - 1):
            v -= 1 << width
        node = out
        for key in path[:-1]:
            node = node.setdefault(key, {})
        node[path[-1]] = v
    return _lists(out)


def _lists(node):
    if isinstance(node, dict):
        node = {k: _lists(v) for k, v in node.items()}
        if node and all(isinstance(k, int) for k in node):
            return [node[i] for i in range(len(node))]
    return node


def pack_array(layout, columns):
    """Pack many records at once. ``columns`` maps each leaf path (a tuple) to an integer array.

    Returns a list of Python ints (records may be wider than 64 bits).
    """
    n = None
    words = None
    for path, offset, shape in leaves(layout):
        col = np.asarray(columns[path], dtype=np.int64)
        if n is None:
            n = len(col)
            words = [0] * n
        mask = (1 << shape.width) - 1
        for i, v in enumerate(col.tolist()):
            words[i] |= (v & mask) << offset
    return words or []


def pack_bytes(layout, columns, *, chunk=1 << 15):
    """:func:`pack_array` as bytes, in bulk: a (n, ceil(size / 8)) uint8 array, each record's
    bytes least significant first (fields of at most 64 bits; for millions of records)."""
    size = data.Layout.cast(layout).size
    fields = list(leaves(layout))
    n = len(columns[fields[0][0]])
    out = np.empty((n, -(-size // 8)), dtype=np.uint8)
    for a in range(0, n, chunk):
        bits = np.zeros((min(chunk, n - a), 8 * out.shape[1]), dtype=np.uint8)
        for path, offset, shape in fields:
            col = np.asarray(columns[path][a:a + chunk], dtype=np.int64).astype(np.uint64)  # two's complement
            bits[:, offset:offset + shape.width] = (col[:, None] >> np.arange(shape.width, dtype=np.uint64)) & 1
        out[a:a + chunk] = np.packbits(bits, axis=1, bitorder="little")
    return out


def unpack_array(layout, words):
    """Inverse of :func:`pack_array`: returns ``{leaf path: int64 array}``."""
    out = {}
    for path, offset, shape in leaves(layout):
        mask = (1 << shape.width) - 1
        col = [(int(w) >> offset) & mask for w in words]
        if shape.signed:
            sign = 1 << (shape.width - 1)
            col = [v - (1 << shape.width) if v & sign else v for v in col]
        out[path] = np.array(col, dtype=np.int64)
    return out


def patch_columns(vertices, normals):
    """Leaf columns of :func:`patch_layout` from integer vertices (N, 3, 3) and normals (N, 3)."""
    cols = {}
    for k, name in enumerate(("v0", "v1", "v2")):
        for a, axis in enumerate("xyz"):
            cols[(name, axis)] = vertices[:, k, a]
    for a, axis in enumerate("xyz"):
        cols[("normal", axis)] = normals[:, a]
    return cols


def point_columns(points):
    """Leaf columns of :func:`point_layout` from integer points (N, 3)."""
    return {(axis,): points[:, a] for a, axis in enumerate("xyz")}
