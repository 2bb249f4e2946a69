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

    python benchmarks/bench_ulx3s_link.py --faults 1e-5 [--traversal board] [--shooters 40]

What link integrity costs (issue 31): the same columns through the framed link
(:mod:`blockray.framing`) to the model (``--board model-link``'s
:class:`~blockray.host_driver.board.framed.ModelBoardLink`) twice in one run, with no faults and
with ``RATE`` faults per byte each way (:class:`~blockray.host_driver.board.framed.LinkFaults`,
seed ``--seed``), the commands made as ``--traversal`` makes them (``board``: rays made on the
board, on the board's lattice grid). The bytes are the wire's (frames, their COBS, CRC and
numbers, every frame resent, the status and acknowledgement frames); the link's time is the busier
direction's wire bytes at ``baud / 10`` bytes a second plus ``TIMEOUT`` of silence per time-out
(a NAK's round trip through the USB bridge is not modelled). The core bytes alone (no framing at
all) give the framing's own share. The two runs' clear fractions must be equal to the bit (checked).
"""

import argparse
import platform
import time

import numpy as np

from _run_header import print_run_header
from blockray.host_driver.scene import builtin
from blockray.link import DEFAULT_BAUD
from blockray.host_driver.board.driver import BoardDriver
from blockray.host_driver.board.framed import FaultyPipe, FramedTransport, LinkFaults, ModelBoardLink
from blockray.host_driver.render.render import Visibility
from blockray.host_driver.board.simulated import ModelTransport
from blockray.host_driver.traverse.board_walk import board_grid
from blockray.host_driver.traverse.voxel import VoxelGrid
from blockray.host_driver.traverse.cost import default_voxels
from blockray.params import BoardParams
from blockray.samples import SampleScheme
from blockray.synth.bitstream import BOARD_BUILDS, DEFAULT_FREQ_MHZ

#: the exact cell's bitstream (``blockray bitstream --cell exact``), whose link docs/ulx3s.md measures
EXACT = BOARD_BUILDS["exact"]

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


def measure(scene_name, shooters, seed, rows=EXACT.rows, cols=EXACT.cols):
    """Bytes on one board's link for the block rays, as the credited link before the framing carried them."""
    scene = builtin.load(scene_name)
    samples = SampleScheme(8)
    params = BoardParams(rows=rows, cols=cols, boards=1, bits=None)
    links = []

    def transport(p, b):
        links.append(Counting(p))
        return links[-1]

    driver = BoardDriver(params, name="ulx3s-link", transport=transport)
    driver.prepare(scene, samples)
    grid = VoxelGrid(scene.patch_vertices, default_voxels(scene.patches, parallelism=1), margin=driver.margin)
    driver.load(grid)
    cycles0 = driver.counters()["board_cycles"]
    link = links[0]
    link.on = True
    vis = Visibility(scene, driver, grid, samples, rows=params.rows, cols=params.cols)
    rng = np.random.default_rng(seed)
    host = time.process_time()
    for i in rng.choice(scene.patches, shooters, replace=False):
        blocks = vis._blocks_for(int(i), np.arange(scene.patches))
        driver.run(blocks)
    host = time.process_time() - host
    c = driver.counters()
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
    ap.add_argument("--rows", type=int, default=EXACT.rows,
                    help=f"array rows (default {EXACT.rows}: the exact bitstream's)")
    ap.add_argument("--cols", type=int, default=EXACT.cols, help=f"array columns (default {EXACT.cols})")
    ap.add_argument("--faults", type=float, default=None, metavar="RATE",
                    help="instead: the framed link with no faults and with RATE faults per byte each way, side by side")
    ap.add_argument("--traversal", default="block", choices=["block", "board"],
                    help="with --faults: the commands of block rays (default) or of rays made on the board")
    args = ap.parse_args()
    if args.faults is not None:
        _integrity(args)
        return
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


#: seconds the framed host waits in silence before it resends (FramedTransport's default)
TIMEOUT = FramedTransport.__init__.__kwdefaults__["timeout"]


def framed_board(scene, rows, cols, traversal, samples, name, pipe=lambda link, b: link):
    """A one-part R x S board: the driver over the framed link (its byte pipe ``pipe(link, b)``,
    faults for example) to a :class:`Counting` model, loaded with the grid ``traversal`` needs.
    Returns (driver, grid, the models, the framed transports)."""
    cores, wires = [], []

    def transport(p, b):
        cores.append(Counting(p))
        wires.append(FramedTransport(pipe(ModelBoardLink(cores[-1]), b), where="bench"))
        return wires[-1]

    driver = BoardDriver(BoardParams(rows=rows, cols=cols, boards=1, bits=None), name=name, transport=transport)
    driver.prepare(scene, samples)
    voxels = default_voxels(scene.patches, parallelism=1)
    grid = (board_grid(driver, voxels) if traversal == "board"
            else VoxelGrid(scene.patch_vertices, voxels, margin=driver.margin))
    driver.load(grid)
    return driver, grid, cores, wires


def framed_columns(scene, rows, cols, traversal, shooters, faults):
    """The columns of ``shooters`` to every patch through the framed link to the model with
    ``faults`` (a LinkFaults; rate 0: none), the commands of ``traversal``. Returns the counts after
    the load (core bytes, wire bytes, frames, time-outs, injected faults) and the clear fractions."""
    samples = SampleScheme(8)
    driver, grid, cores, wires = framed_board(
        scene, rows, cols, traversal, samples, "ulx3s-link",
        lambda link, b: FaultyPipe(link, faults.injector(b, 0), faults.injector(b, 1)))
    w0 = wires[0].stats()
    cores[0].on = True
    vis = Visibility(scene, driver, grid, samples, rows=rows, cols=cols, traversal=traversal)
    host = time.process_time()
    frac = np.concatenate([vis.clear_fraction(int(i), np.arange(scene.patches)) for i in shooters])
    host = time.process_time() - host
    c, w = driver.counters(), wires[0].stats()
    driver.close()
    injected = {k: sum(w["injected"][d][k] - w0["injected"][d][k] for d in ("to_board", "from_board"))
                for k in w["injected"]["to_board"]}
    return {"rays": c["rays"], "bits": driver.params.bits, "host_seconds": host,
            "down": cores[0].sent, "up": cores[0].received,
            "down_wire": w["wire_bytes_sent"] - w0["wire_bytes_sent"],
            "up_wire": w["wire_bytes_received"] - w0["wire_bytes_received"],
            "frames_sent": w["host"]["frames_sent"] - w0["host"]["frames_sent"],
            "board_frames_sent": w["board_model"]["frames_sent"] - w0["board_model"]["frames_sent"],
            "host_resent": w["host"]["frames_resent"] - w0["host"]["frames_resent"],
            "board_resent": w["board_model"]["frames_resent"] - w0["board_model"]["frames_resent"],
            "host_errors": w["host"]["errors"] - w0["host"]["errors"],
            "board_errors": w["board_model"]["errors"] - w0["board_model"]["errors"],
            "timeouts": w["host"]["timeouts"] - w0["host"]["timeouts"], "injected": injected}, frac


def _integrity(args):
    """The framed link with no faults and at ``--faults``, side by side: bytes, resends, time-outs
    and rays/s through the UART (each time-out costs ``TIMEOUT`` seconds of silence)."""
    print_run_header()
    scene = builtin.load(args.scene)
    shooters = np.random.default_rng(args.seed).choice(scene.patches, args.shooters, replace=False)
    bps = args.baud / 10
    runs, fracs = {}, {}
    for rate in (0.0, args.faults):
        start = time.perf_counter()
        runs[rate], fracs[rate] = framed_columns(scene, args.rows, args.cols, args.traversal, shooters,
                                                 LinkFaults(rate, args.seed))
        runs[rate]["wall"] = time.perf_counter() - start
    assert np.array_equal(fracs[0.0], fracs[args.faults]), "the faults changed a clear fraction"
    f0 = runs[0.0]
    assert all(runs[args.faults][k] == f0[k] for k in ("rays", "down", "up")), "the faults changed the core bytes"
    rays = f0["rays"]
    core_rate = rays * bps / max(f0["down"], f0["up"])
    print(f"{args.scene} ({scene.patches} patches), B = {f0['bits']}, {args.rows} x {args.cols} x 1, "
          f"--traversal {args.traversal}, {args.shooters} shooter columns to every patch, seed {args.seed}: {rays} rays; "
          f"core bytes {f0['down'] / rays:.3f} B/ray to the board, {f0['up'] / rays:.3f} back "
          f"(no framing: {core_rate:,.0f} rays/s through {args.baud} baud)")
    print("| faults per byte | to board B/ray | to host B/ray | frames host / board | resent host / board | "
          "errors host / board | time-outs | injected flip / drop / dup | link seconds | rays/s | of no faults | "
          "of no framing | wall s |")
    print("|---|---|---|---|---|---|---|---|---|---|---|---|---|")
    for rate, r in runs.items():
        seconds = max(r["down_wire"], r["up_wire"]) / bps + r["timeouts"] * TIMEOUT
        r["rate"] = rays / seconds
        inj = r["injected"]
        print(f"| {rate:g} | {r['down_wire'] / rays:.3f} | {r['up_wire'] / rays:.3f} | {r['frames_sent']} / "
              f"{r['board_frames_sent']} | {r['host_resent']} / {r['board_resent']} | {r['host_errors']} / "
              f"{r['board_errors']} | {r['timeouts']} | {inj['flipped']} / {inj['dropped']} / {inj['duplicated']} | "
              f"{seconds:.3f} | {r['rate']:,.0f} | {r['rate'] / f0['rate']:.4f} | {r['rate'] / core_rate:.4f} | "
              f"{r['wall']:.0f} |", flush=True)
    r = runs[args.faults]
    print(f"link integrity at {args.faults:g} faults per byte: {1 - r['rate'] / f0['rate']:.2%} of the fault-free "
          f"framed link's rays/s, {1 - r['rate'] / core_rate:.2%} of the unframed core bytes' (framing alone: "
          f"{1 - f0['rate'] / core_rate:.2%}); clear fractions equal to the bit")


if __name__ == "__main__":
    main()
