"""The point unit's arithmetic, shared by its gateware (:class:`blockray.rtl.points.PointUnit`) and
its bit-exact model (:func:`blockray.sim.points.point_of`): a shooter's sample point or a
receiver's end point from a patch record, as the board makes rays itself (docs/board-protocol.md,
"Rays made on the board: design").

A point is (w0 V0 + w1 V1 + w2 V2) / D for a weight triple summing to D (``SampleScheme.weights``;
the centroid is (p, p, p) times the end lattice). The vertices of every record are multiples of D
(docs/fixed-point.md), so the division is exact: with D = d 2^e (d odd), the numerator shifted
right by e is d times the point, and the point is that times d's inverse modulo 2^B, its low B
bits. No divider: a shift and a multiply.
"""

from dataclasses import dataclass
import numbers

from .errors import ParameterError
from .params import check_bits

__all__ = ["PointArithmetic", "POINT_LATENCY"]

#: the point unit's cycle contract: its point is valid in the 13th cycle after the cycle its job
#: was taken (nine multiply-accumulates, a weight times a vertex coordinate each, then three
#: multiplies by d^-1, one product a cycle on its one multiplier), and it takes no job meanwhile
POINT_LATENCY = 1 + 9 + 3


@dataclass(frozen=True)
class PointArithmetic:
    """The constants of the exact division by ``denominator`` (D) on the ``bits``-bit grid (B):
    ``shift`` (e), ``inverse`` (d^-1 mod 2^B), ``weight_bits`` (a weight, 0 to D) and
    ``sum_bits`` (the numerator, at most D (2^B - 1))."""

    bits: int
    denominator: int

    def __post_init__(self):
        check_bits(self.bits)
        D = self.denominator
        if isinstance(D, bool) or not isinstance(D, numbers.Integral) or D < 1:
            raise ParameterError(f"the sample denominator must be a positive integer, not {D!r}",
                                 parameter="denominator")

    @property
    def shift(self):
        D = self.denominator
        return (D & -D).bit_length() - 1

    @property
    def inverse(self):
        return pow(self.denominator >> self.shift, -1, 1 << self.bits)

    @property
    def weight_bits(self):
        return self.denominator.bit_length()

    @property
    def sum_bits(self):
        return self.bits + self.weight_bits
