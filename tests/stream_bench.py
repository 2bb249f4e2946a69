"""The Amaranth-simulator bench the stream unit tests share (test_points.py, test_ray_walk.py,
test_rtl_sequencer.py): random idle on the input stream and back-pressure on the output, seeded."""

from amaranth.sim import Simulator


def drive_streams(dut, source, sink, items, rng, step, *, payload, until, offer=0.7, accept=0.6):
    """Simulate ``dut``: each cycle offer the first of ``items`` on stream ``source`` (its payload
    ``payload(item)``) with probability ``offer`` and raise ``sink.ready`` with probability
    ``accept``, settle, then call ``step(ctx, cycle, taken)``, ``taken`` the item ``source``
    transferred in this cycle or None; until ``until()`` is true."""
    pending = list(items)

    async def bench(ctx):
        cycle = 0
        while not until():
            offered = bool(pending) and rng.random() < offer
            ctx.set(source.valid, offered)
            if offered:
                ctx.set(source.payload, payload(pending[0]))
            ctx.set(sink.ready, rng.random() < accept)
            await ctx.delay(1e-9)
            step(ctx, cycle, pending.pop(0) if offered and ctx.get(source.ready) else None)
            cycle += 1
            await ctx.tick()

    sim = Simulator(dut)
    sim.add_clock(1e-8)
    sim.add_testbench(bench)
    sim.run()
