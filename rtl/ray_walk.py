"""The ray walker: the integer 3D DDA of one ray of a block on the board's lattice grid, the
stepper of rays made on the board (docs/board-protocol.md, "Rays made on the board"; its model is
:mod:`blockray.block_walk`, which the host's ``--traversal board`` runs). Not wired into the board
yet: the block sequencer will feed it a block's rays and expand its boxes into voxels, once each.

::

    jobs (p, q, grid) --> box at t = 0 --> box at each crossing of grid planes, in order of t --> boxes

A box is the index range [lo, hi] per axis (clipped to the grid, up to 2 x 2 x 2 voxels, ``empty``
when the clipping leaves none) of the voxels whose closed box holds the ray's point at that t:
expanded x outer, z inner, each voxel at its first box, they are exactly the voxels the kernel
walks. The next crossing is the least t = num_c / |d_c| over the axes still crossing planes, the
fractions compared by cross-multiplication; equal ones cross together. One box a cycle: box k of
a job is valid in the (k + 1)-th cycle after the cycle the job was taken, the last flagged
``last``, and the next job is taken after it has left.
"""

from amaranth.hdl import Cat, Module, Mux, Signal, signed, unsigned
from amaranth.lib import data, stream, wiring
from amaranth.lib.wiring import In, Out
from amaranth.utils import bits_for

from ..board_rays import MAX_GRID
from ..params import check_bits
from ..records import point_layout

__all__ = ["RayWalker", "walk_job_layout", "box_layout"]


def walk_job_layout(bits):
    """A job: the ray's end points and the grid (origin, voxel edge 2^shift, v voxels per axis)."""
    point = point_layout(bits)
    return data.StructLayout({"p": point, "q": point, "origin": point,
                              "shift": unsigned(bits_for(bits)), "v": unsigned(bits_for(MAX_GRID))})


def box_layout():
    """A box of voxel indices, clipped to the grid; ``empty`` when none is left, ``last`` on a
    ray's final box."""
    index = data.ArrayLayout(unsigned(bits_for(MAX_GRID - 1)), 3)
    return data.StructLayout({"lo": index, "hi": index, "empty": unsigned(1), "last": unsigned(1)})


class RayWalker(wiring.Component):
    """``jobs`` (In, :func:`walk_job_layout`) -> ``boxes`` (Out, :func:`box_layout`), B = ``bits``."""

    def __init__(self, *, bits):
        self._bits = check_bits(bits)
        super().__init__({"jobs": In(stream.Signature(walk_job_layout(bits))),
                          "boxes": Out(stream.Signature(box_layout()))})

    def elaborate(self, platform):
        m = Module()
        B = self._bits
        wide = signed(B + 4)                                # coordinates, planes and indices, signed
        job = self.jobs.payload
        shift, v = Signal.like(job.shift), Signal.like(job.v)
        x, d, cell, plane, lo, hi = ([Signal(wide, name=f"{n}_{c}") for c in "xyz"]
                                     for n in ("x", "d", "cell", "plane", "lo", "hi"))
        ad = [Signal(unsigned(B + 1), name=f"ad_{c}") for c in "xyz"]
        num = [Signal(wide, name=f"num_{c}") for c in "xyz"]
        live = [Signal(name=f"live_{c}") for c in "xyz"]
        for c in range(3):                                  # the next crossing of each axis: t = num / ad
            m.d.comb += num[c].eq(Mux(d[c] > 0, (plane[c] << shift) - x[c], x[c] - (plane[c] << shift)))
            m.d.comb += live[c].eq((d[c] != 0) & (num[c] <= ad[c]))
        # axis c crosses next (with any equal ones) when its t is at most every live axis' t; the six
        # products num_a |d_b| once each (each enters two comparisons), B x B bits: a comparison
        # counts only when both axes are live, and then 0 < num_a <= |d_a| < 2^B
        product = {(a, b): Signal(unsigned(2 * B), name=f"num_{'xyz'[a]}_ad_{'xyz'[b]}")
                   for a in range(3) for b in range(3) if a != b}
        m.d.comb += [prod.eq(num[a][:B] * ad[b][:B]) for (a, b), prod in product.items()]
        first = [Signal(name=f"first_{c}") for c in "xyz"]
        for c in range(3):
            m.d.comb += first[c].eq(live[c])
            for b in range(3):
                if b != c:
                    with m.If(live[b] & (product[c, b] > product[b, c])):
                        m.d.comb += first[c].eq(0)
        self._output(m, lo, hi, v, live)

        with m.FSM(init="Take"):
            with m.State("Take"):
                m.d.comb += self.jobs.ready.eq(1)
                with m.If(self.jobs.valid):
                    self._start(m, job, shift, v, x, d, ad, cell, plane, lo, hi)
                    m.next = "Walk"
            with m.State("Walk"):
                m.d.comb += self.boxes.valid.eq(1)
                with m.If(self.boxes.ready):
                    with m.If(~Cat(*live).any()):
                        m.next = "Take"
                    for c in range(3):
                        up = d[c] > 0
                        with m.If(first[c]):                # on the plane: both neighbours
                            m.d.sync += [lo[c].eq(plane[c] - 1), hi[c].eq(plane[c]),
                                         cell[c].eq(Mux(up, plane[c], plane[c] - 1)),
                                         plane[c].eq(Mux(up, plane[c] + 1, plane[c] - 1))]
                        with m.Elif(d[c] != 0):
                            m.d.sync += [lo[c].eq(cell[c]), hi[c].eq(cell[c])]
        return m

    def _start(self, m, job, shift, v, x, d, ad, cell, plane, lo, hi):
        """Take a job: the box at t = 0 and each axis' open cell and next plane."""
        m.d.sync += [shift.eq(job.shift), v.eq(job.v)]
        for c, name in enumerate("xyz"):
            p, q, o = (Signal(x[c].shape(), name=f"{n}_{name}") for n in ("p", "q", "o"))   # signed: differences
            m.d.comb += [p.eq(job.p[name]), q.eq(job.q[name]), o.eq(job.origin[name])]
            xc, dc = p - o, q - p
            a = -((-xc) >> job.shift) - 1                   # ceil(x / L) - 1
            b = xc >> job.shift                             # floor(x / L)
            m.d.sync += [x[c].eq(xc), d[c].eq(dc), ad[c].eq(Mux(dc < 0, -dc, dc)), lo[c].eq(a), hi[c].eq(b),
                         cell[c].eq(Mux(dc > 0, b, a)), plane[c].eq(Mux(dc > 0, b + 1, a))]

    def _output(self, m, lo, hi, v, live):
        """The held box, clipped to [0, v - 1]; last when no axis crosses another plane."""
        box, empty = self.boxes.payload, []
        for c in range(3):
            clo = Mux(lo[c] < 0, 0, lo[c])
            chi = Mux(hi[c] > v - 1, v - 1, hi[c])
            m.d.comb += [box.lo[c].eq(clo), box.hi[c].eq(chi)]
            empty.append((hi[c] < 0) | (lo[c] > v - 1) | (lo[c] > hi[c]))
        m.d.comb += [box.empty.eq(Cat(*empty).any()), box.last.eq(~Cat(*live).any())]
