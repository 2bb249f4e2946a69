"""The serial transport without hardware: a missing port and a silent board fail in seconds with
one line (exit 2 from the CLI); over a pseudo-terminal, a board written here from the link's
framing definition (credits, frames) exchanges bytes with the transport."""

import os
import random
import threading
import time

import pytest

from blockray.cli import main
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
    """A board on the master side of a pty, from the framing definition: ``depth`` credits
    granted once ``released`` is set (the host ended its break), every command byte b answered with the
    result b ^ 0x5A in frames of random length, a grant per few bytes taken. Records whether the
    host ever sent beyond its credits."""

    def __init__(self, fd, *, depth, seed):
        super().__init__(daemon=True)
        self.fd, self.depth, self.rng = fd, depth, random.Random(seed)
        self.released = threading.Event()      # a pty carries no break: the test's transport says
        self.overrun = False
        self.received = 0
        self.stop = False

    def run(self):
        try:
            self._serve()
        except OSError:         # the test closed the pty
            pass

    def _serve(self):
        self.released.wait()
        os.write(self.fd, bytes([0x80 | (self.depth - 1)]))
        owed, granted, pending = 0, self.depth, bytearray()
        while not self.stop:
            data = os.read(self.fd, 64)
            self.received += len(data)
            if self.received > granted:
                self.overrun = True
            pending += bytes(b ^ 0x5A for b in data)
            owed += len(data)
            out = bytearray()
            while pending:
                n = min(len(pending), self.rng.randint(1, 128))
                out.append(n - 1)
                out += pending[:n]
                del pending[:n]
            if owed >= self.rng.randint(1, self.depth):
                out.append(0x80 | (owed - 1))
                granted += owed
                owed = 0
            os.write(self.fd, bytes(out))
            if owed:                # grant the rest soon, so the host is never left waiting
                time.sleep(0.01)
                os.write(self.fd, bytes([0x80 | (owed - 1)]))
                granted += owed
                owed = 0


def test_credits_and_frames_over_a_pty(pty_pair):
    seed = 7
    print("seed", seed)
    master, name = pty_pair
    board = PtyBoard(master, depth=16, seed=seed)
    board.start()
    rng = random.Random(seed)
    data = bytes(rng.randrange(256) for _ in range(600))

    class Transport(SerialTransport):
        def _set_break(self, on):
            super()._set_break(on)
            if not on:
                board.released.set()

    with Transport(name, answer_timeout=5.0, timeout=5.0) as link:
        got = bytearray()
        for i in range(0, len(data), 50):
            link.send(data[i:i + 50])
            got += link.recv(rng.randint(0, 50 + i - len(got)))
        got += link.recv(len(data) - len(got))
        stats = link.stats()
    board.stop = True
    assert bytes(got) == bytes(b ^ 0x5A for b in data)
    assert not board.overrun and stats["bytes_sent"] == len(data)
