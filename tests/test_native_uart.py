"""The native UART bridge (sim/native/uart_harness.cpp, ``--board ulx3s-sim``'s default) against the
cocotb one (sim/uart_cocotb.py): the same top at its pins, the same host code and faults, so the two
must give the same bytes, the same link counters and the same simulated clock cycles, cycle for
cycle: the cocotb bridge is the oracle (it shares no code with the C++ loop)."""

import random

import pytest

from blockray.host_driver.board.framed import LinkFaults
from blockray.host_driver.board.uart_sim import UartSimTransport
from blockray.rtl.link import EchoCore

from link_cores import echo

pytestmark = pytest.mark.cocotb


def _session(native, seed):
    """Bytes through an echo core with faults both ways and a reset mid-way: what came back, the
    link's counters and the clock cycles the simulation ran."""
    rng = random.Random(seed)
    data = bytes(rng.randrange(256) for _ in range(600))
    with UartSimTransport(EchoCore(repeat=2), faults=LinkFaults(3e-3, seed, record=True), name="blockray_uart_echo",
                          native=native) as link:
        got = bytearray(link.recv(0))
        link.send(data[:100])
        got += link.recv(60)
        link.reset()
        got = bytearray()
        for i in range(0, len(data), 200):
            link.send(data[i:i + 200])
            got += link.recv(rng.randint(0, 2 * (i + 200) - len(got)))
        got += link.recv(2 * len(data) - len(got))
        stats = link.stats()
        cycles = link.pipe.pipe.cycles
    return bytes(got), stats, cycles, data


@pytest.mark.parametrize("seed", [3, pytest.param(8, marks=pytest.mark.slow)])
def test_native_bridge_runs_the_cocotb_bridges_cycles(seed):
    print("seed", seed)
    native, cocotb = _session(True, seed), _session(False, seed)
    assert native[0] == echo(native[3], 2)
    assert native[1]["injected"] == cocotb[1]["injected"] and sum(native[1]["injected"]["to_board"].values()) > 0
    assert native[1] == cocotb[1]
    assert native[2] == cocotb[2] > 0
