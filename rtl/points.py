"""The point unit: a shooter's sample point or a receiver's end point from a patch record, on the
board's integer grid, exactly as the host computes it (``SampleScheme.points_int`` /
``centroids_int``; the arithmetic: :mod:`blockray.points`). The first unit of rays made on the
board (docs/board-protocol.md, "Rays made on the board: design"); not wired into the board yet.

::

    jobs (patch record, weights) --> 9 x acc[c] += w[j] V[j][c] --> 3 x point[c] = (acc[c] >> e) d^-1 --> points

One multiplier, used once a cycle: a job's point is valid :attr:`PointUnit.latency` cycles (13)
after the cycle its job was taken, and the next job is taken after its point has left.
"""

from amaranth.hdl import Array, Module, Mux, Signal, unsigned
from amaranth.lib import data, stream, wiring
from amaranth.lib.wiring import In, Out

from ..board_rays import MAX_DENOMINATOR
from ..points import POINT_LATENCY, PointArithmetic
from ..records import patch_layout, point_layout

__all__ = ["PointUnit", "point_job_layout"]


def point_job_layout(arithmetic):
    """A job: the patch record as board memory holds it and the three weights (each 0 to D)."""
    return data.StructLayout({"patch": patch_layout(arithmetic.bits),
                              "weights": data.ArrayLayout(unsigned(arithmetic.weight_bits), 3)})


class PointUnit(wiring.Component):
    """``jobs`` (In, :func:`point_job_layout`) -> ``points`` (Out, :func:`~blockray.records.point_layout`
    of B bits). ``bits``: B; ``denominator``: D, the weights' sum, or None for a D the board
    learns (``LOAD_SAMPLES``): then e and d^-1 are inputs ``shift`` and ``inverse``, held while
    a job runs, and the weights are :data:`~blockray.board_rays.WEIGHT_BITS` wide. The point is
    exact for records whose vertices are multiples of D (every quantised scene's); latency
    :attr:`latency` cycles, one job at a time."""

    def __init__(self, *, bits, denominator=None):
        self._learnt = denominator is None
        self._arith = PointArithmetic(bits, MAX_DENOMINATOR if self._learnt else denominator)
        ports = {"jobs": In(stream.Signature(point_job_layout(self._arith))),
                 "points": Out(stream.Signature(point_layout(bits)))}
        if self._learnt:                    # MAX_DENOMINATOR sets the widths only
            ports |= {"shift": In(range(self._arith.weight_bits)), "inverse": In(bits)}
        super().__init__(ports)

    @property
    def arithmetic(self):
        return self._arith

    @property
    def latency(self):
        """:data:`~blockray.points.POINT_LATENCY`: the point is valid in the 13th cycle after its
        job's transfer."""
        return POINT_LATENCY

    def elaborate(self, platform):
        m = Module()
        a = self._arith
        job = Signal(point_job_layout(a))
        acc = Array(Signal(a.sum_bits, name=f"acc_{c}") for c in "xyz")
        out = Signal(point_layout(a.bits))
        coord, vertex = Signal(range(3)), Signal(range(3))      # the product's coordinate and vertex

        patch = job.patch
        coords = Array(Array(v[c] for c in "xyz") for v in (patch.v0, patch.v1, patch.v2))
        shift, inverse = (self.shift, self.inverse) if self._learnt else (a.shift, a.inverse)
        scaled = (acc[coord] >> shift)[:a.bits]
        product = Signal(a.sum_bits + a.bits)
        multiply = Signal()                                     # the inverse's multiplies, not the sums
        m.d.comb += product.eq(Mux(multiply, scaled * inverse, job.weights[vertex] * coords[vertex][coord]))
        m.d.comb += self.points.payload.eq(out)

        with m.FSM(init="Take"):
            with m.State("Take"):
                m.d.comb += self.jobs.ready.eq(1)
                with m.If(self.jobs.valid):
                    m.d.sync += [job.eq(self.jobs.payload), coord.eq(0), vertex.eq(0)]
                    m.d.sync += [acc[c].eq(0) for c in range(3)]
                    m.next = "Sum"
            with m.State("Sum"):                                # acc[c] += w[j] V[j][c], c outer
                m.d.sync += acc[coord].eq(acc[coord] + product)
                m.d.sync += vertex.eq(Mux(vertex == 2, 0, vertex + 1))
                with m.If(vertex == 2):
                    m.d.sync += coord.eq(Mux(coord == 2, 0, coord + 1))
                    with m.If(coord == 2):
                        m.next = "Divide"
            with m.State("Divide"):                             # the exact division: a multiply
                m.d.comb += multiply.eq(1)
                for c, name in enumerate("xyz"):
                    with m.If(coord == c):
                        m.d.sync += out[name].eq(product[:a.bits])
                m.d.sync += coord.eq(coord + 1)
                with m.If(coord == 2):
                    m.next = "Give"
            with m.State("Give"):
                m.d.comb += self.points.valid.eq(1)
                with m.If(self.points.ready):
                    m.next = "Take"
        return m
