"""The lean array's test bench, shared by the Amaranth simulator (tests/test_lean.py) and cocotb +
Verilator (tests/cocotb_lean.py): ``LeanBench`` (the array and the patch memory its records come
from) and ``StepDriver`` (the owner's side: steps presented under the credits, as the board)."""

from amaranth.hdl import Module, unsigned
from amaranth.lib import wiring
from amaranth.lib.memory import Memory

from blockray.records import pack, patch_layout, point_layout
from blockray.rtl.lean import LeanArray
from blockray.sim.lean_model import Gap, Mark, Record


class LeanBench(wiring.Component):
    """:class:`LeanArray` with its patch memory (initialised with ``words``) on the second read
    port; every other port of the array is the bench's."""

    def __init__(self, bits, rows, cols, fmt, depth, words):
        self.array = LeanArray(bits, rows, cols, fmt=fmt, depth=depth,
                               address_bits=max(1, (len(words) - 1).bit_length()))
        self.memory = Memory(shape=unsigned(patch_layout(bits).size), depth=max(2, len(words)), init=words)
        super().__init__({k: v for k, v in self.array.signature.members.items() if k != "patch_read"})

    def elaborate(self, platform):
        m = Module()
        m.submodules.array = a = self.array
        m.submodules.patches = self.memory
        read = self.memory.read_port()
        m.d.comb += [read.addr.eq(a.patch_read.addr), read.en.eq(a.patch_read.en), a.patch_read.data.eq(read.data)]
        for name, member in self.signature.members.items():
            outer, inner = getattr(self, name), getattr(a, name)
            m.d.comb += inner.eq(outer) if member.flow == wiring.In else outer.eq(inner)
        return m


class StepDriver:
    """Presents ``steps`` (sim.lean_model) one per cycle: a record or marker waits while
    ``depth`` items are inside (presented and not delivered), a gap never does. Per cycle:
    :meth:`inputs` (port name -> packed value), then :meth:`observe` with the outputs read
    before the clock edge. Collects the cycle each step is presented, each marker's cycle and
    ``hit`` then."""

    def __init__(self, steps, words, bits, rows, cols, depth):
        self.steps, self.words, self.rows, self.cols, self.depth = steps, words, rows, cols, depth
        self._point, self._width = point_layout(bits), point_layout(bits).size
        self.presented, self.marks, self.hits = [], [], []
        self.inside = self.t = self.i = 0
        self._issue = False

    @property
    def done(self):
        return self.i >= len(self.steps) and self.inside == 0

    def _points(self, points):
        return sum(pack(self._point, dict(zip("xyz", map(int, p)))) << (k * self._width)
                   for k, p in enumerate(points))

    def inputs(self):
        step = self.steps[self.i] if self.i < len(self.steps) else Gap()
        self._issue = not isinstance(step, Gap) and self.inside < self.depth
        self._go = isinstance(step, Gap) or self._issue
        values = {"valid": int(self._issue and isinstance(step, Record)),
                  "mark": int(self._issue and isinstance(step, Mark))}
        if isinstance(step, Record):
            values.update(first=int(step.first), address=step.address, patch=self.words[step.address],
                          row_mask=int(sum(int(b) << r for r, b in enumerate(step.row_mask))),
                          col_mask=int(sum(int(b) << s for s, b in enumerate(step.col_mask))),
                          shooters=self._points(step.shooters), receivers=self._points(step.receivers))
        else:       # garbage on the data inputs while no record is presented
            values.update(patch=0x5A5A5A5A, address=self.t % len(self.words))
        return values

    def observe(self, delivered, mark_out, hit):
        if mark_out:
            self.marks.append(self.t)
            self.hits.append(hit)
        if self._go and self.i < len(self.steps):
            self.presented.append(self.t)
            self.i += 1
        self.inside += int(self._issue) - delivered
        self.t += 1
