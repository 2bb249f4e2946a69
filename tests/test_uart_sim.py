"""The simulated real board's link under Verilator (cocotb): the same top as on the ULX3S
(SerialLink: UART, framed link) with the link's test core, driven through the same host code as
a real board (FramedTransport) over the simulated UART pins, with a reset (break) mid-way and
faults injected both ways; the board's own counters read over the link."""

import random

import pytest

from blockray.host_driver.board.framed import LinkFaults
from blockray.host_driver.board.uart_sim import UartSimTransport
from blockray.rtl.link import EchoCore

from link_cores import echo

pytestmark = pytest.mark.cocotb


def test_echo_through_the_simulated_uart():
    seed = 21
    print("seed", seed)
    rng = random.Random(seed)
    data = bytes(rng.randrange(256) for _ in range(900))
    with UartSimTransport(EchoCore(repeat=2), faults=LinkFaults(2e-3, seed), name="blockray_uart_echo",
                          timeout=2.0) as link:
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
    # the board's counters, read over the link: it saw the faults sent to it and resent frames
    board = stats["board"]
    assert board["errors"] > 0 and board["frames_resent"] > 0
    assert board["frames_accepted"] >= -(-len(data) // 254)
