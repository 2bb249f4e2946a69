"""Bit-exact model of the point unit (:class:`blockray.rtl.points.PointUnit`): the point it
computes and the cycles it takes (:data:`~blockray.points.POINT_LATENCY`, the cycle contract
the gateware is tested against)."""

from ..points import POINT_LATENCY

__all__ = ["point_of", "POINT_LATENCY"]


def point_of(vertices, weights, arithmetic):
    """The point of weights (w0, w1, w2) on vertices ((x, y, z) x 3), as the unit computes it:
    the low B bits of ((sum_j w_j V_j) >> e) d^-1, per coordinate, in Python integers."""
    a = arithmetic
    mask = (1 << a.bits) - 1
    return tuple(((sum(w * v[c] for w, v in zip(weights, vertices)) >> a.shift) * a.inverse) & mask
                 for c in range(3))
