"""The simulated real board's link under Verilator (cocotb): the same top as on the ULX3S
(SerialLink: UART, FIFOs, credits) with the link's test core, driven through the same host code
as a real board (CreditedLink) over the simulated UART pins, with a reset (break) mid-way."""

import random

import pytest

from blockray.host_driver.uart_sim import UartSimTransport
from blockray.rtl.link import EchoCore

from link_cores import echo

pytestmark = pytest.mark.cocotb


def test_echo_through_the_simulated_uart():
    seed = 21
    print("seed", seed)
    rng = random.Random(seed)
    data = bytes(rng.randrange(256) for _ in range(400))
    with UartSimTransport(EchoCore(repeat=2), fifo_depth=16, result_depth=16, name="blockray_uart_echo") as link:
        assert link.credits == 16                       # all the FIFO's credits, granted after the reset
        link.send(data[:150])
        assert link.recv(100) == echo(data[:50], 2)
        link.reset()                                    # the rest of the first part is lost
        assert link.credits == 16
        got = bytearray()
        for i in range(0, 400, 40):
            link.send(data[i:i + 40])
            got += link.recv(rng.randint(0, 2 * (i + 40) - len(got)))
        got += link.recv(2 * len(data) - len(got))
        stats = link.stats()
    assert bytes(got) == echo(data, 2)
    assert stats["bytes_sent"] == 550 and stats["resets"] == 2
