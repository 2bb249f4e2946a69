"""The simulated real board's link under Verilator (cocotb): the same top as on the ULX3S
(SerialLink: UART, framed link) with the link's test core, driven through the same host code as
a real board (FramedTransport) over the simulated UART pins, with a reset (break) mid-way and
faults injected both ways; the board's own counters read over the link match what the faults
imply (tests/link_oracle.py). The simulation runs in lockstep with the host, so its time-outs
count clock cycles and the run is the same under any load."""

import random

import pytest

from blockray.host_driver.board.framed import LinkFaults
from blockray.host_driver.board.uart_sim import UartSimTransport
from blockray.rtl.link import EchoCore

import link_oracle
from link_cores import echo

pytestmark = pytest.mark.cocotb


def test_echo_through_the_simulated_uart():
    seed = 21
    print("seed", seed)
    rng = random.Random(seed)
    data = bytes(rng.randrange(256) for _ in range(900))
    with UartSimTransport(EchoCore(repeat=2), faults=LinkFaults(2e-3, seed, record=True),
                          name="blockray_uart_echo") as link:
        link.send(data[:150])
        assert link.recv(100) == echo(data[:50], 2)
        link.reset()                                    # the rest of the first part is lost
        assert link.endpoint.next == 0
        got = bytearray()
        for i in range(0, len(data), 300):
            link.send(data[i:i + 300])
            got += link.recv(rng.randint(0, 2 * (i + 300) - len(got)))
        got += link.recv(2 * len(data) - len(got))
        stats = link.stats()
    print(stats)
    assert bytes(got) == echo(data, 2)
    assert stats["resets"] == 2
    injected = stats["injected"]
    assert sum(injected["to_board"].values()) > 0 and sum(injected["from_board"].values()) > 0
    # since the reset: the board saw every fault sent to it, the host every fault sent to it,
    # and each side resent every first send that was hit
    board, host, pipe = stats["board"], stats["host"], link.pipe
    hits = [link_oracle.check_direction(pipe.outgoing, errors=board["errors"], resent=host["frames_resent"],
                                        where="to the board"),
            link_oracle.check_direction(pipe.incoming, errors=host["errors"], resent=board["frames_resent"],
                                        where="from the board")]
    assert all(bad > 0 for bad, _ in hits)       # the seed puts faults both ways after the reset
    assert board["frames_accepted"] >= -(-len(data) // 254)


class _Planted:
    """``faults`` for the transport: the host's data frame 1 and the board's data frame 0 hit on
    their first send and on their resend (tests/link_oracle.py ``Planted``)."""

    def injector(self, board, direction):
        return link_oracle.Planted(seq=1 - direction)


def test_a_resent_frame_hit_again_recovers_without_a_time_out():
    """The gateware's receiver NAKs again at the host's POLL that ends a resend round (and at the
    host's RESEND while its gap is open); the gateware's sender ends its resend rounds with a
    POLL, which the host answers so. Both resent frames hit again are recovered with no time-out
    of the host (in simulated time: the link is in lockstep)."""
    data = bytes(random.Random(4).randrange(256) for _ in range(300))
    with UartSimTransport(EchoCore(repeat=2), faults=_Planted(), name="blockray_uart_echo") as link:
        link.send(data)
        got = link.recv(2 * len(data))
        stats = link.stats()
        cycles = link.pipe.pipe.cycles
    print(stats, "simulated cycles", cycles)
    assert got == echo(data, 2)
    board, host, pipe = stats["board"], stats["host"], link.pipe
    assert pipe.outgoing.counts["flipped"] == pipe.incoming.counts["flipped"] == 2
    link_oracle.check_direction(pipe.outgoing, errors=board["errors"], resent=host["frames_resent"],
                                where="to the board")
    link_oracle.check_direction(pipe.incoming, errors=host["errors"], resent=board["frames_resent"],
                                where="from the board")
    assert host["naks_sent"] >= 2 and host["timeouts"] == 0
