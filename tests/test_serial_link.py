"""The serial transport without hardware: a missing port and a silent board fail in seconds with
one line (exit 2 from the CLI); over a pseudo-terminal, the board's half of the framed link
exchanges bytes with the transport, and its counters are read over it."""

import os
import random
import threading
import time
import tty

import pytest

from blockray.cli import main
from blockray.framing import BOARD_LINK, Endpoint
from blockray.host_driver.serial_link import SerialTransport
from blockray.host_driver.transport import TransportError


@pytest.fixture
def pty_pair():
    master, slave = os.openpty()
    yield master, os.ttyname(slave)
    os.close(slave)
    os.close(master)


def test_missing_port():
    t0 = time.monotonic()
    with pytest.raises(TransportError, match=r"^--port /dev/blockray-none: cannot open the serial port"):
        SerialTransport("/dev/blockray-none")
    assert time.monotonic() - t0 < 2


def test_silent_board(pty_pair):
    _, name = pty_pair
    t0 = time.monotonic()
    with pytest.raises(TransportError, match="no answer from the board within 1 s"):
        SerialTransport(name, answer_timeout=1.0)
    assert time.monotonic() - t0 < 3


@pytest.mark.parametrize("port", ["/dev/blockray-none", None])
def test_cli_render_without_a_board(port, pty_pair, capsys):
    port = port or pty_pair[1]
    t0 = time.monotonic()
    code = main(["render", "cornell", "--board", "ulx3s", "--boards", "1", "--rows", "2", "--cols", "2",
                 "--port", port, "--quiet"])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and len(err) == 1 and err[0].startswith(f"blockray: error: --port {port}: "), err
    assert time.monotonic() - t0 < 10


def test_cli_render_needs_a_port(capsys):
    assert main(["render", "cornell", "--board", "ulx3s", "--boards", "1", "--quiet"]) == 2
    assert capsys.readouterr().err.startswith("blockray: error: --port")


class PtyBoard(threading.Thread):
    """A board on the master side of a pty: the board's half of the framed link (an
    :class:`~blockray.framing.Endpoint` with the board's frame sizes) in front of a core that
    answers every command byte b with b ^ 0x5A; the pty's bytes are read in random pieces."""

    def __init__(self, fd, *, seed):
        super().__init__(daemon=True)
        self.fd, self.rng = fd, random.Random(seed)
        self.endpoint = Endpoint(BOARD_LINK)
        self.stop = False

    def run(self):
        try:
            while not self.stop:
                data = os.read(self.fd, self.rng.randint(1, 300))
                self.endpoint.submit(bytes(b ^ 0x5A for b in self.endpoint.receive(data)))
                os.write(self.fd, self.endpoint.output())
        except OSError:         # the test closed the pty
            pass


def test_framed_link_over_a_pty(pty_pair):
    seed = 7
    print("seed", seed)
    master, name = pty_pair
    tty.setraw(master)
    board = PtyBoard(master, seed=seed)
    board.start()
    rng = random.Random(seed)
    data = bytes(rng.randrange(256) for _ in range(3000))
    with SerialTransport(name, answer_timeout=5.0) as link:
        got = bytearray()
        for i in range(0, len(data), 500):
            link.send(data[i:i + 500])
            got += link.recv(rng.randint(0, 500 + i - len(got)))
        got += link.recv(len(data) - len(got))
        stats = link.stats()
    board.stop = True
    assert bytes(got) == bytes(b ^ 0x5A for b in data)
    # the board's counters came over the link: each send's frames (of at most 246 bytes) accepted once
    assert stats["board"]["frames_accepted"] == stats["host"]["frames_sent"] == 6 * -(-500 // 246)
    assert stats["board"]["errors"] == stats["host"]["errors"] == 0
