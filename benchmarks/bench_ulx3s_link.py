"""The ULX3S's serial link against the array: bytes per ray each way, rays per second through a
UART, and the array's own rate.

    python benchmarks/bench_ulx3s_link.py [--scene cornell] [--shooters 40] [--seed 1] [--clock 45] [--baud 3000000]
                                          [--rows 1 --cols 2]

A one-part board, by default the array ``blockray bitstream`` builds (1 x 2 at B = 16, docs/ulx3s.md): the renderer's
block rays of ``--shooters`` random shooter columns go through the host driver over the bit-exact
model behind the link (:class:`~blockray.host_driver.board.simulated.ModelTransport`, counted here at
the transport: every byte the driver sends and receives, identify and load excluded). The link's
own framing is added (:mod:`blockray.link`): a header byte per result frame (counted as one frame
per result record: the board sends each as it forms, at UART pace) and a credit grant byte per
32 command bytes (the bridge's batch while results wait; at most). A UART moves 10 bits per byte,
so ``baud / 10`` bytes per second each way; the array's own rate is rays / board cycles x clock.
"""

import argparse
import platform
import time

import numpy as np

from blockray.host_driver.scene import builtin
from blockray.link import DEFAULT_BAUD
from blockray.host_driver.board.driver import BoardDriver
from blockray.host_driver.board.framed import FaultyPipe, FramedTransport, LinkFaults, ModelBoardLink
from blockray.host_driver.render.render import Visibility
from blockray.host_driver.board.simulated import ModelTransport
from blockray.host_driver.traverse.voxel import VoxelGrid
from blockray.host_driver.traverse.cost import default_voxels
from blockray.params import BoardParams
from blockray.samples import SampleScheme
from blockray.synth.bitstream import DEFAULT_COLS, DEFAULT_FREQ_MHZ, DEFAULT_ROWS

GRANT_BATCH = 32


class Counting(ModelTransport):
    """ModelTransport that counts bytes and result reads while ``on``."""

    def __init__(self, params):
        super().__init__(params)
        self.on = False
        self.sent = self.received = self.reads = 0

    def send(self, data):
        if self.on:
            self.sent += len(data)
        super().send(data)

    def recv(self, count, *, timeout=None):
        if self.on:
            self.received += count
            self.reads += 1
        return super().recv(count, timeout=timeout)

    def run(self, data=b"", *, whole=True):
        out = super().run(data, whole=whole)
        if self.on and not whole:           # behind the framed link (recv counts the others)
            self.received += len(out)
        return out


def _framed(core, faults):
    """The framed link (blockray.framing) over ``core``, with ``faults`` injected."""
    pipe = ModelBoardLink(core)
    return FramedTransport(FaultyPipe(pipe, faults.injector(0, 0), faults.injector(0, 1)), where="bench")


def measure(scene_name, shooters, seed, rows=DEFAULT_ROWS, cols=DEFAULT_COLS, faults=None):
    """Bytes on one board's link for the block rays; ``faults``: through the framed link with
    them (:class:`~blockray.host_driver.board.framed.LinkFaults`), else the credited link's figures."""
    scene = builtin.load(scene_name)
    samples = SampleScheme(8)
    params = BoardParams(rows=rows, cols=cols, boards=1, bits=None)
    links, outer = [], []

    def transport(p, b):
        links.append(Counting(p))
        outer.append(links[-1] if faults is None else _framed(links[-1], faults))
        return outer[-1]

    driver = BoardDriver(params, name="ulx3s-link", transport=transport)
    driver.prepare(scene, samples)
    grid = VoxelGrid(scene.patch_vertices, default_voxels(scene.patches, parallelism=1), margin=driver.margin)
    driver.load(grid)
    cycles0 = driver.counters()["board_cycles"]
    link = links[0]
    link.on = True
    wire0 = outer[0].stats()
    vis = Visibility(scene, driver, grid, samples, rows=params.rows, cols=params.cols)
    rng = np.random.default_rng(seed)
    host = time.process_time()
    for i in rng.choice(scene.patches, shooters, replace=False):
        blocks = vis._blocks_for(int(i), np.arange(scene.patches))
        driver.run(blocks)
    host = time.process_time() - host
    c = driver.counters()
    if faults is not None:
        wire = outer[0].stats()
        return {"rays": c["rays"], "host_seconds": host, "down": link.sent, "up": link.received,
                "down_wire": wire["wire_bytes_sent"] - wire0["wire_bytes_sent"],
                "up_wire": wire["wire_bytes_received"] - wire0["wire_bytes_received"],
                "timeouts": wire["host"]["timeouts"] - wire0["host"]["timeouts"], **c["link_integrity"]}
    proto = driver.protocol
    from blockray.protocol import ResultKind
    nb = proto.result_bytes(ResultKind.BLOCKED)
    records = c["blocks"] + (link.received - c["blocks"] * nb) // proto.result_bytes(ResultKind.COUNTERS)
    return {"scene": scene_name, "patches": scene.patches, "bits": driver.params.bits, "rays": c["rays"],
            "host_seconds": host,
            "blocks": c["blocks"], "board_cycles": c["board_cycles"] - cycles0,
            "down": link.sent, "up": link.received, "records": records,
            "down_wire": link.sent, "up_wire": link.received + records + -(-link.sent // GRANT_BATCH)}


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scene", default="cornell")
    ap.add_argument("--shooters", type=int, default=40)
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--clock", type=float, default=DEFAULT_FREQ_MHZ,
                    help=f"board clock, MHz (default {DEFAULT_FREQ_MHZ:g}: blockray bitstream's)")
    ap.add_argument("--baud", type=int, default=DEFAULT_BAUD)
    ap.add_argument("--rows", type=int, default=DEFAULT_ROWS, help=f"array rows (default {DEFAULT_ROWS}: the bitstream's)")
    ap.add_argument("--cols", type=int, default=DEFAULT_COLS, help=f"array columns (default {DEFAULT_COLS})")
    ap.add_argument("--faults", type=float, default=None, metavar="RATE",
                    help="also measure the framed link (issue 31) with RATE faults per byte each way")
    args = ap.parse_args()
    r = measure(args.scene, args.shooters, args.seed, args.rows, args.cols)
    rays = r["rays"]
    bps = args.baud / 10
    down, up = r["down_wire"] / rays, r["up_wire"] / rays
    link_rate = bps / max(down, up)
    array_rate = rays / r["board_cycles"] * args.clock * 1e6
    print(f"machine: {platform.machine()}, python {platform.python_version()}; {args.scene} ({r['patches']} patches), "
          f"B = {r['bits']}, {args.rows} x {args.cols} x 1, seed {args.seed}, {args.shooters} shooter columns: {r['blocks']} blocks, "
          f"{rays} rays, {r['board_cycles']} board cycles")
    print(f"host -> board: {r['down']} command bytes = {r['down'] / rays:.2f} B/ray (no framing that way)")
    print(f"board -> host: {r['up']} result bytes in {r['records']} records + headers + grants = "
          f"{r['up_wire']} B = {up:.2f} B/ray")
    print(f"link: {bps / 1e3:.0f} kB/s each way at {args.baud} baud -> {link_rate:,.0f} rays/s "
          f"(bound by {'host -> board' if down >= up else 'board -> host'})")
    print(f"array: {rays / r['board_cycles']:.3f} rays/cycle x {args.clock:g} MHz = {array_rate:,.0f} rays/s; "
          f"the link is {array_rate / link_rate:.1f}x slower")
    for name, rate in (("USB 1.1 full speed on the ULX3S's US2 port (~1 MB/s bulk)", 1e6),
                       ("FT2232H synchronous FIFO (~40 MB/s)", 40e6), ("PCIe Gen2 x1 (~400 MB/s)", 400e6)):
        r_link = rate / max(r["down_wire"], r["up_wire"] - r["records"]) * rays
        print(f"{name}: link {r_link:,.0f} rays/s; the board {min(r_link, array_rate):,.0f} rays/s, "
              f"{min(r_link, array_rate) / link_rate:.1f}x the UART ({'link' if r_link < array_rate else 'array'}-bound; "
              f"the link could feed {r_link / array_rate:.2f} such arrays)")
    if args.faults is not None:
        _integrity(args, r, link_rate, bps)


#: seconds the framed host waits in silence before it resends (FramedTransport's default)
TIMEOUT = FramedTransport.__init__.__kwdefaults__["timeout"]


def _integrity(args, plain, plain_rate, bps):
    """The framed link at ``--faults`` against the credited link (``plain``): its bytes, resends,
    time-outs and rays/s through the UART (each time-out costs ``TIMEOUT`` seconds of silence)."""
    f = measure(args.scene, args.shooters, args.seed, args.rows, args.cols, faults=LinkFaults(args.faults, args.seed))
    rays = f["rays"]
    assert (f["down"], f["up"]) == (plain["down"], plain["up"]), "the framed link carried other core bytes"
    seconds = max(f["down_wire"], f["up_wire"]) / bps + f["timeouts"] * TIMEOUT
    rate = rays / seconds
    print(f"framed link at {args.faults:g} faults per byte each way (seed {args.seed}): host -> board "
          f"{f['down_wire'] / rays:.2f} B/ray, board -> host {f['up_wire'] / rays:.2f} B/ray, "
          f"{(f['down_wire'] + f['up_wire']) / rays:.2f} B/ray together (credited: "
          f"{(plain['down_wire'] + plain['up_wire']) / rays:.2f}); {f['frames_sent']} frames sent, "
          f"{f['frames_resent']} resent, {f['errors']} errors, {f['timeouts']} time-outs of {TIMEOUT * 1e3:g} ms; "
          f"injected {f.get('injected_flipped', 0)} flips, {f.get('injected_dropped', 0)} drops, "
          f"{f.get('injected_duplicated', 0)} duplicates")
    print(f"framed link: {rate:,.0f} rays/s through the UART, {1 - rate / plain_rate:.1%} fewer than the credited "
          f"link's {plain_rate:,.0f}; host CPU {f['host_seconds'] / rays * 1e6:.1f} us/ray (credited "
          f"{plain['host_seconds'] / rays * 1e6:.1f})")


if __name__ == "__main__":
    main()
