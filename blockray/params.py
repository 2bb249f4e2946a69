"""Board parameters: one object configures the bit-exact model, the RTL and synthesis."""

from dataclasses import dataclass, fields, replace

from .errors import ParameterError

__all__ = ["BoardParams", "Widths", "check_bits", "MIN_BITS", "MAX_BITS"]


@dataclass(frozen=True)
class Widths:
    """Bit widths of the exact intersection arithmetic, all derived from ``bits`` (B) here only.

    Coordinates are unsigned B-bit integers in ``[0, 2**B - 1]`` (L = 2**B - 1).

    ``coord``  B       vertex and sample-point coordinates (unsigned)
    ``diff``   B + 1   P - V, Q - V, edge vectors V[k+1] - V[k] (signed)
    ``cross``  2B + 2  normals and row terms w = (Q - V) x e: |component| <= 2 L**2 < 2**(2B+1) (signed)
    ``orient`` 3B + 2  every orient3d value: |det| <= 2 L**3 < 2**(3B+1) (signed); the product
                       terms of a dot product may wrap modulo 2**orient, the sum is still exact.
    """

    bits: int

    @property
    def coord(self):
        return self.bits

    @property
    def diff(self):
        return self.bits + 1

    @property
    def cross(self):
        return 2 * self.bits + 2

    @property
    def orient(self):
        return 3 * self.bits + 2


MIN_BITS = 4
MAX_BITS = 20   # the numpy int64 model is exact up to 3B + 2 = 62 bits


def check_bits(bits):
    """``bits`` (as an int) if B is an integer from :data:`MIN_BITS` to :data:`MAX_BITS`, else
    :class:`ParameterError` about parameter ``bits``."""
    import numbers
    if isinstance(bits, bool) or not isinstance(bits, numbers.Integral) or not MIN_BITS <= bits <= MAX_BITS:
        raise ParameterError(f"bits must be an integer from {MIN_BITS} to {MAX_BITS} (the exact arithmetic "
                             f"needs 3*B+2 <= 62 bits), not {bits!r}", parameter="bits")
    return int(bits)


@dataclass(frozen=True)
class BoardParams:
    """Parameters of one board and of the machine made of ``boards`` of them.

    rows         R: receivers per block (rows of the processor array)
    cols         S: shooter sample points per block (columns of the processor array)
    boards       P: boards, each holding a disjoint partition of the patches
    bits         B: coordinate bits of the quantised scene; None: chosen for the scene when a
                 board quantises it (its params carry the B it chose from then on)
    patch_depth  words of patch memory per board (one word = one patch record; a patch
                 registered in k voxels takes k words)
    voxel_depth  entries of the voxel table per board (at least v**3)
    """

    rows: int = 8
    cols: int = 8
    boards: int = 8
    bits: int | None = 16
    patch_depth: int = 1 << 14
    voxel_depth: int = 1 << 15

    def __post_init__(self):
        for f in fields(self):
            value = getattr(self, f.name)
            if f.name == "bits":               # None, or B by its own rule below
                continue
            if isinstance(value, bool) or not isinstance(value, int):
                raise ParameterError(f"board parameter {f.name} must be an integer, not {value!r}",
                                     parameter=f.name)
            if value < 1:
                raise ParameterError(f"board parameter {f.name} must be at least 1, not {value}",
                                     parameter=f.name)
        if self.bits is not None:
            check_bits(self.bits)
        if self.rows > 64 or self.cols > 64:
            raise ParameterError(f"array of {self.rows} x {self.cols} processors: rows and cols must be at most 64",
                                 parameter="rows" if self.rows > 64 else "cols")

    @property
    def widths(self):
        if self.bits is None:
            raise ParameterError("bits: B is chosen for a scene when a board quantises it; the widths need "
                                 "it resolved", parameter="bits")
        return Widths(self.bits)

    @property
    def processors(self):
        """Processors per board (R x S)."""
        return self.rows * self.cols

    def with_(self, **changes):
        return replace(self, **changes)
