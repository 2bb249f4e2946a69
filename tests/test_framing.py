"""Link integrity (blockray/framing.py, host_driver/board/framed.py): the CRC against independent
implementations, frames, resynchronisation after garbage, the go-back-N window, two endpoints
over a faulty line, and renders through ``--board model-link --link-faults`` that must equal the
fault-free render byte for byte or end with exit 2 and one line. Seeded; the seeds are printed."""

import binascii
import random
import zlib

import pytest

from blockray.host_driver.cli import main
from blockray.framing import (MAX_PAYLOAD, POLL, RESEND, Endpoint, Frame, FrameError, FrameSplitter, LinkConfig, crc32,
                              encode_frame, parse_frame, wire_frame_bytes)
from blockray.host_driver.board.framed import FaultInjector, FaultyPipe, FramedTransport, LinkFaults, ModelBoardLink
from blockray.host_driver.board.driver import BoardDriver
from blockray.host_driver.render.render import render
from blockray.host_driver.board.simulated import ModelTransport
from blockray.host_driver.board.transport import TransportError

import clirun
from scenes import RTL_PARAMS, room_scene


def _bitwise_crc32(data):
    """CRC-32/ISO-HDLC one bit at a time (reflected polynomial 0xEDB88320): what the RTL computes."""
    crc = 0xFFFFFFFF
    for byte in data:
        crc ^= byte
        for _ in range(8):
            crc = crc >> 1 ^ (0xEDB88320 if crc & 1 else 0)
    return crc ^ 0xFFFFFFFF


def test_crc32_matches_known_implementations(rng_seed):
    seed = rng_seed
    rng = random.Random(seed)
    assert crc32(b"123456789") == 0xCBF43926            # the catalogue's check value
    for n in (0, 1, 2, 7, 64, 253, 1000):
        data = bytes(rng.randrange(256) for _ in range(n))
        assert crc32(data) == binascii.crc32(data) == _bitwise_crc32(data) == zlib.crc32(data) & 0xFFFFFFFF


def test_frame_round_trip_and_size():
    for payload in (b"", b"\x00", b"\x00" * MAX_PAYLOAD, bytes(range(256))[:MAX_PAYLOAD]):
        frame = Frame(RESEND, 255, 17, payload)
        wire = encode_frame(frame)
        assert wire[-1] == 0 and 0 not in wire[:-1]
        assert len(wire) == wire_frame_bytes(len(payload))
        assert parse_frame(wire[:-1]) == frame
    with pytest.raises(ValueError):
        encode_frame(Frame(0, 0, 0, b"x" * (MAX_PAYLOAD + 1)))


def test_every_flip_drop_and_duplicate_of_a_frame_is_detected():
    wire = encode_frame(Frame(0, 3, 9, bytes(range(1, 41))))[:-1]
    bad = []
    for i in range(len(wire)):
        bad += [wire[:i] + bytes([wire[i] ^ 1 << b]) + wire[i + 1:] for b in range(8)]
        bad += [wire[:i] + wire[i + 1:], wire[:i] + wire[i:i + 1] * 2 + wire[i + 1:]]
    for chunk in bad:
        for part in chunk.split(b"\x00"):           # a flip to zero cuts the frame in two
            if part:
                with pytest.raises(FrameError):
                    parse_frame(part)


def test_resynchronises_after_garbage(rng_seed):
    seed = rng_seed
    rng = random.Random(seed)
    frames = [Frame(0, k, 0, bytes([k + 1]) * 5) for k in range(20)]
    stream = bytearray()
    for f in frames:
        stream += bytes(rng.randrange(256) for _ in range(rng.randrange(40))) + b"\x00"   # garbage, cut
        stream += encode_frame(f)
    stream += bytes(rng.randrange(1, 256) for _ in range(3000))     # overlong garbage: dropped, bounded
    stream += b"\x00" + encode_frame(frames[0])
    splitter, got, overlong = FrameSplitter(), [], 0
    for i in range(0, len(stream), 7):                              # in small pieces
        chunks, _ = splitter.feed(stream[i:i + 7])
        assert len(splitter._buf) <= FrameSplitter.limit
        for c in chunks:
            if c is None:                           # the overlong chunk, at its delimiter
                overlong += 1
                continue
            try:
                got.append(parse_frame(c))
            except FrameError:
                pass
    assert got == frames + frames[:1] and overlong == 1


def _pump(a, b, faults_ab=None, faults_ba=None, rounds=10000):
    """Run endpoint a against b until both have delivered everything (a: the host, with time-outs)."""
    got_a, got_b = bytearray(), bytearray()
    for _ in range(rounds):
        out = a.output()
        got_b += b.receive(faults_ab(out) if faults_ab else out)
        back = b.output()
        got_a += a.receive(faults_ba(back) if faults_ba else back)
        if not a.pending and not b.pending:
            return bytes(got_a), bytes(got_b)
        if not back:
            a.rewind()
    raise AssertionError("no progress")


def test_go_back_n_wraps_sequence_numbers_and_keeps_the_window():
    cfg = LinkConfig(payload=3, window=127)
    a, b = Endpoint(cfg), Endpoint(LinkConfig(payload=5, window=1))
    data = bytes(random.Random(1).randrange(256) for _ in range(3 * 700))   # 700 frames: wraps 256 twice
    a.submit(data)
    b.submit(data[:900])
    first = a.output()
    assert first.count(b"\x00") == 127                                      # the window, no more
    assert a.output() == b""                                                # nothing before an ack
    got_b = b.receive(first)
    got_a, rest = _pump(a, b)
    assert got_b + rest == data and got_a == data[:900]
    assert a.counts["frames_resent"] == 0 and a.faults() == b.faults() == 0


def test_no_frame_accepted_twice_or_out_of_order():
    a, b = Endpoint(LinkConfig(payload=1, window=4)), Endpoint(LinkConfig())
    a.submit(b"wxyz")
    frames = [f + b"\x00" for f in a.output().split(b"\x00")[:-1]]
    assert b.receive(frames[1]) == b""                                  # out of order: a gap
    assert b.counts["out_of_order"] == 1
    assert b.receive(frames[0] + frames[0]) == b"w"                     # the second is a duplicate
    assert b.counts["duplicate"] == 1
    # 2 before 1: a new gap; then 1, 1 again, 2, 3
    assert b.receive(frames[2] + frames[1] + frames[1] + frames[2] + frames[3]) == b"xyz"
    assert b.expect == 4 and b.counts["frames_accepted"] == 4
    assert b.counts["out_of_order"] == 2 and b.counts["duplicate"] == 2


def test_ack_and_resend_edge_cases():
    a, b = Endpoint(LinkConfig(payload=2, window=3)), Endpoint(LinkConfig())
    a.submit(b"aabbccdd")
    wire = a.output()
    assert a.next == 3 and len(a._unacked) == 3
    a.receive(encode_frame(Frame(0, 0, 200, b"")))                      # an impossible ack: ignored
    assert a.base == 0
    a.receive(encode_frame(Frame(0, 0, 2, b"")))                        # frames 0 and 1 acknowledged
    assert a.base == 2 and len(a._unacked) == 1
    more = a.output()                                                   # frame 3 enters the window
    assert more.count(b"\x00") == 1
    a.receive(encode_frame(Frame(RESEND, 0, 2, b"")))                   # NAK: resend 2 and 3, then a POLL
    again = a.output()
    assert again.count(b"\x00") == 3 and a.counts["frames_resent"] == 2
    assert parse_frame(again.split(b"\x00")[2]) == Frame(POLL, 4, 0, b"")
    assert b.receive(wire + again) == b"aabbccdd"


@pytest.mark.parametrize("rate", [1e-3, 1e-2, 3e-2])
def test_endpoints_over_a_faulty_line_deliver_exactly(rate, rng_seed):
    seed = rng_seed
    rng = random.Random(seed)
    import numpy as np
    a, b = Endpoint(LinkConfig(payload=60, window=8)), Endpoint(LinkConfig(payload=60, window=8))
    up = bytes(rng.randrange(256) for _ in range(20000))
    down = bytes(rng.randrange(256) for _ in range(5000))
    a.submit(up)
    b.submit(down)
    ab = FaultInjector(rate, np.random.default_rng([seed, 0]))
    ba = FaultInjector(rate, np.random.default_rng([seed, 1]))
    got_a, got_b = _pump(a, b, ab, ba, rounds=200000)
    assert got_b == up and got_a == down
    assert sum(ab.counts.values()) > 0 and a.counts["frames_resent"] > 0


def test_fault_injector_is_seeded_and_counts():
    data = bytes(range(256)) * 400
    one = FaultInjector(1e-3, LinkFaults(1e-3, 5).injector(0, 0).rng)
    two = LinkFaults(1e-3, 5).injector(0, 0)
    assert one(data) == two(data) != data
    assert one.counts == two.counts and 50 < sum(one.counts.values()) < 160
    assert FaultInjector(0, None)(data) == data
    with pytest.raises(Exception, match="^link_faults must be a rate per byte"):
        LinkFaults(1.5)


def test_the_board_counters_read_over_the_link_are_the_boards():
    """A model board's own counts, and the same counts as the host reads them in a status frame."""
    seed = 12
    print("seed", seed)
    faults = LinkFaults(2e-3, seed)
    pipe = FaultyPipe(_Mirror(), faults.injector(0, 0), faults.injector(0, 1))
    link = FramedTransport(pipe, where="test", answer_timeout=5.0)
    link.reset()
    data = bytes(random.Random(seed).randrange(256) for _ in range(20000))
    link.send(data)
    assert link.recv(len(data)) == bytes(b ^ 0xFF for b in data)
    pipe.outgoing.rate = pipe.incoming.rate = 0          # the counters' exchange itself unharmed
    stats = link.stats()
    own = stats["board_model"]
    assert sum(pipe.outgoing.counts.values()) > 0 and own["errors"] > 0 and own["frames_resent"] > 0
    assert stats["board"] == {k: own[k] for k in ("frames_resent", "errors", "frames_accepted")}


class _Mirror(ModelBoardLink):
    """The board's half of the link in front of a core that inverts every byte."""

    def __init__(self):
        super().__init__(core=None)
        self._out = bytearray()

    def write(self, data):
        self._out += bytes(b ^ 0xFF for b in self.endpoint.receive(data))

    def read(self, timeout):
        self.endpoint.submit(bytes(self._out))
        self._out.clear()
        return self.endpoint.output()

    def reset(self):
        self.endpoint.reset()


class _Silent:
    def write(self, data):
        pass

    def read(self, timeout):
        return b""

    def reset(self):
        pass


def test_a_silent_board_fails_naming_the_link():
    link = FramedTransport(_Silent(), where="--port /dev/ttyFAKE", timeout=0.01, max_retries=5)
    link.send(b"\x07")
    with pytest.raises(TransportError, match=r"^--port /dev/ttyFAKE: the link failed: no progress in 5 time-outs.*no answer"):
        link.recv(1)


# -- renders through --board model-link --link-faults ---------------------------------------------

RENDER = ["--max-edge", "1.5", "--board", "model-link", "--rows", "2", "--cols", "2", "--boards", "2",
          "--bits", "10", "--samples", "4", "--max-shots", "2", "--voxels", "3", "--quiet"]


@pytest.fixture(scope="module")
def room(tmp_path_factory):
    return clirun.room_render(tmp_path_factory.mktemp("framing_room"), RENDER)


#: seeds for which the small room's ~30 kB of link traffic meets faults even at 1e-5 (seed 24: two)
@pytest.mark.parametrize("rate,seed", [(1e-5, 24), (1e-4, 4), (1e-3, 5), (1e-3, 6)])
def test_render_with_link_faults_is_byte_identical(room, tmp_path, rate, seed):
    integrity = clirun.faulty_render(room, tmp_path, RENDER, rate, seed)
    # faults were injected, and corrected by resending
    assert integrity["injected_flipped"] + integrity["injected_dropped"] + integrity["injected_duplicated"] > 0
    assert integrity["frames_resent"] > 0 and integrity["errors"] > 0


def test_render_at_a_hopeless_fault_rate_ends_with_exit_2(room, tmp_path, capsys):
    clirun.hopeless_render(capsys, room, tmp_path, RENDER, "model-link board 0")


def test_link_faults_need_a_framed_board(room, capsys):
    path, _ = room
    assert main(["render", str(path), *RENDER[:2], "--board", "model", "--link-faults", "1e-3", "--quiet"]) == 2
    assert ("--link-faults needs a board with a framed link (--board model-link or ulx3s-sim or ulx3s)"
            in capsys.readouterr().err)


class _Flipper(ModelTransport):
    """An unframed model link that flips the tag of the first blocked word (bits 1:0 = 3)."""

    def recv(self, count, *, timeout=None):
        data = bytearray(super().recv(count, timeout=timeout))
        if count > 31:                      # a batch of blocks, not IDENTIFY or the load's counters
            data[0] |= 3
        return bytes(data)


def test_a_corrupted_result_tag_on_an_unframed_link_is_one_error(room):
    """Without framing (a board on the old serial link) a corrupted result header is a
    TransportError naming the board, not a ValueError."""
    path, _ = room
    scene = room_scene(path.parent, 1.5)
    board = BoardDriver(RTL_PARAMS, transport=lambda p, b: _Flipper(p))
    with pytest.raises(TransportError, match=r"board 0 \(the link\): a corrupted result: result tag 3"):
        render(scene, board=board, params=RTL_PARAMS, bits=10, samples=4, max_shots=1, voxels=3)


@pytest.mark.parametrize("to_board,from_board", [(1, None), (None, 0), (1, 0)],
                         ids=["to_board", "from_board", "both_ways"])
def test_a_resent_frame_hit_again_is_asked_for_again_without_a_time_out(to_board, from_board):
    """Planted faults (tests/link_oracle.py ``Planted``), no rate: the host's data frame ``to_board``
    and the board's data frame ``from_board`` are hit on their first send and again on their
    resend. The POLL after a resend round finds the frame still missing (and, both ways, the
    RESEND of a side whose NAK went with a lost frame), so the receiver asks again: at least two
    NAKs where a frame was hit, and the host never times out (a receiver that NAKs once per gap
    leaves it to the host's time-out). Each side's errors are the corrupted chunks."""
    import link_oracle
    outgoing, incoming = (link_oracle.Planted(seq) if seq is not None else link_oracle.Planted(-1)
                          for seq in (to_board, from_board))
    pipe = FaultyPipe(_Mirror(), outgoing, incoming)
    link = FramedTransport(pipe, where="test", answer_timeout=5.0)
    link.reset()
    data = bytes(random.Random(3).randrange(256) for _ in range(2000))
    link.send(data)
    assert link.recv(len(data)) == bytes(b ^ 0xFF for b in data)
    board, host = pipe.pipe.endpoint, link.endpoint
    print("board", board.counts, "host", host.counts)
    for seq, injector, receiver, sender in ((to_board, outgoing, board, host), (from_board, incoming, host, board)):
        hit = seq is not None
        assert injector.counts["flipped"] == 2 * hit
        link_oracle.check_direction(injector, errors=receiver.faults(), resent=sender.counts["frames_resent"],
                                    where="to the board" if receiver is board else "from the board")
        assert (receiver.counts["naks_sent"] >= 2) == hit
    assert host.counts["timeouts"] == 0
