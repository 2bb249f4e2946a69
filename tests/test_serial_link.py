"""The serial transport without hardware: a missing port and a silent board fail in seconds with
one line (exit 2 from the CLI); over a pseudo-terminal, a board written here from the link's
framing definition (credits, frames) exchanges bytes with the transport."""

import os
import random
import select
import threading
import time

import numpy as np
import pytest

from blockray.cli import main
from blockray.host_driver.backends import build_board
from blockray.host_driver.builtin import load_scene
from blockray.host_driver.options import RenderOptions
from blockray.host_driver.render import render
from blockray.host_driver.serial_link import SerialTransport
from blockray.params import BoardParams
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
            if not select.select([self.fd], [], [], 0.05)[0]:
                continue            # (a read would hold the thread past the test, on a reused fd)
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
    board.join(timeout=5)
    assert bytes(got) == bytes(b ^ 0x5A for b in data)
    assert not board.overrun and stats["bytes_sent"] == len(data)


class ModelPtyBoard(PtyBoard):
    """A ULX3S on the master side of a pty, answered by the bit-exact model built for ``params``
    (the bitstream's configuration): once ``released`` (the host ended its reset break) it grants
    ``depth`` credits; it runs the commands through the model as they come, sends their results in
    frames and grants back a credit for every command byte taken."""

    def __init__(self, fd, params, *, depth=64):
        from blockray.host_driver.simulated import ModelTransport
        super().__init__(fd, depth=depth, seed=0)
        self.model = ModelTransport(params)

    def _serve(self):
        from blockray.link import frame_results, grant_header
        self.released.wait()
        os.write(self.fd, bytes([grant_header(self.depth)]))
        while not self.stop:
            if not select.select([self.fd], [], [], 0.05)[0]:
                continue
            data = os.read(self.fd, 4096)
            out = bytearray(frame_results(self.model.run(data, whole=False)))
            for k in range(0, len(data), 128):
                out.append(grant_header(min(128, len(data) - k)))
            os.write(self.fd, bytes(out))


@pytest.fixture
def ulx3s_on_a_pty(pty_pair, monkeypatch):
    """A board built as its bitstream (B = 14, its own memories) on a pty; the serial transport's
    reset releases it."""
    master, name = pty_pair
    built = BoardParams(rows=2, cols=2, boards=1, bits=14, patch_depth=20000, voxel_depth=4096)
    board = ModelPtyBoard(master, built)
    unbreak = SerialTransport._set_break

    def set_break(self, on):
        unbreak(self, on)
        if not on:
            board.released.set()
    monkeypatch.setattr(SerialTransport, "_set_break", set_break)
    board.start()
    yield name, built
    board.stop = True
    board.join(timeout=5)


def test_ulx3s_board_from_the_registry_takes_its_configuration_from_identify(ulx3s_on_a_pty):
    """``--board ulx3s`` is built by the registry over the serial port: the host is told R, S and
    P only, the board's IDENTIFY gives B and the memories; the render equals the model's."""
    name, built = ulx3s_on_a_pty
    scene = load_scene("cornell")
    run = dict(rows=2, cols=2, boards=1, samples=4, max_shots=2, voxels=4)
    options = RenderOptions.of(backend="ulx3s", port=name, **run)
    with build_board(options.board) as board:
        assert board.params == built                   # from IDENTIFY, before anything is uploaded
        real = render(scene, board, options)
    model = render(scene, backend="model", bits=14, **run)
    assert np.array_equal(real.radiosity, model.radiosity)
    for key in ("bits", "tests", "tests_issued", "board_cycles", "board_cycles_per_board", "rays", "blocks"):
        assert real.report[key] == model.report[key], key
    assert real.report["board"] == "ulx3s" and real.report["bits"] == 14
    assert real.report["driver"]["params"]["patch_depth"] == 20000


def test_ulx3s_board_refuses_another_configuration(ulx3s_on_a_pty, capsys):
    name, _ = ulx3s_on_a_pty
    code = main(["render", "cornell", "--board", "ulx3s", "--port", name, "--boards", "1", "--rows", "2",
                 "--cols", "2", "--bits", "16", "--max-shots", "1", "--quiet"])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and err == ["blockray: error: board 0 was built for another configuration: bits 14 (host 16)"]
