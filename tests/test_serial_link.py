"""The serial transport without hardware: a missing port and a silent board fail in seconds with
one line (exit 2 from the CLI); over a pseudo-terminal, the board's half of the framed link
exchanges bytes with the transport, and its counters are read over it; the registry's ulx3s
board over a pty answered by the model."""

import os
import random
import select
import threading
import time
import tty

import numpy as np
import pytest

from blockray.cell import Cell
from blockray.host_driver.cli import main
from blockray.framing import BOARD_LINK, Endpoint
from blockray.host_driver.board.backends import build_board
from blockray.host_driver.scene.builtin import load_scene
from blockray.host_driver.render.options import RenderOptions
from blockray.host_driver.render.render import render
from blockray.host_driver.board.serial_link import SerialTransport
from blockray.params import BoardParams
from blockray.host_driver.board.transport import TransportError


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
                if not select.select([self.fd], [], [], 0.05)[0]:
                    continue
                data = os.read(self.fd, self.rng.randint(1, 300))
                self.endpoint.submit(self.core(self.endpoint.receive(data)))
                os.write(self.fd, self.endpoint.output())
        except OSError:         # the test closed the pty
            pass

    def core(self, commands):
        return bytes(b ^ 0x5A for b in commands)


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


class ModelPtyBoard(PtyBoard):
    """A ULX3S on the master side of a pty, answered by the bit-exact model built for ``params``
    (the bitstream's configuration) behind the board's half of the framed link; ``rays``: built
    with the block sequencer (IDENTIFY version 5, as ``blockray bitstream`` builds it)."""

    def __init__(self, fd, params, *, rays=True, cell=Cell()):
        from blockray.host_driver.board.simulated import ModelTransport
        super().__init__(fd, seed=0)
        self.model = ModelTransport(params, rays=rays, **({"cell": cell} if cell.filtered else {}))

    def core(self, commands):
        return self.model.run(commands, whole=False)


def _board_on_a_pty(pty_pair, **built_with):
    master, name = pty_pair
    tty.setraw(master)
    built = BoardParams(rows=2, cols=2, boards=1, bits=14, patch_depth=20000, voxel_depth=4096)
    board = ModelPtyBoard(master, built, **built_with)
    board.start()
    yield name, built
    board.stop = True
    board.join(timeout=5)


@pytest.fixture(params=[True], ids=["rays"])
def ulx3s_on_a_pty(pty_pair, request):
    """A board built as its bitstream (B = 14, its own memories; with the block sequencer unless
    the test asks otherwise, ``indirect``) on a pty."""
    yield from _board_on_a_pty(pty_pair, rays=request.param)


@pytest.fixture
def lean_ulx3s_on_a_pty(pty_pair):
    """The same board built with the lean cell (``blockray bitstream --cell lean``)."""
    yield from _board_on_a_pty(pty_pair, cell=Cell("lean"))


@pytest.mark.parametrize("ulx3s_on_a_pty", [True, False], ids=["rays", "no-rays"], indirect=True)
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


def test_ulx3s_board_makes_its_rays(ulx3s_on_a_pty):
    """A bitstream built with the block sequencer answers IDENTIFY version 5, so ``--board ulx3s``
    takes ``--traversal board``: the render equals the model's with the same traversal."""
    name, _ = ulx3s_on_a_pty
    scene = load_scene("cornell")
    run = dict(rows=2, cols=2, boards=1, samples=4, max_shots=1, traversal="board")
    options = RenderOptions.of(backend="ulx3s", port=name, **run)
    with build_board(options.board) as board:
        real = render(scene, board, options)
        assert [i["version"] for i in board.identities] == [5]
    model = render(scene, backend="model", bits=14, **run)
    assert np.array_equal(real.radiosity, model.radiosity)
    for key in ("tests", "tests_issued", "board_cycles", "rays", "blocks"):
        assert real.report[key] == model.report[key], key


@pytest.mark.parametrize("ulx3s_on_a_pty", [False], ids=["no-rays"], indirect=True)
def test_ulx3s_board_without_the_sequencer_refuses_board_rays(ulx3s_on_a_pty, capsys):
    """A bitstream without the block sequencer (IDENTIFY version 4) renders block rays, and
    ``--traversal board`` is refused before any ray command is sent."""
    name, _ = ulx3s_on_a_pty
    code = main(["render", "cornell", "--board", "ulx3s", "--port", name, "--boards", "1", "--rows", "2",
                 "--cols", "2", "--max-shots", "1", "--traversal", "board", "--quiet"])
    err = capsys.readouterr().err.strip().splitlines()
    errors = [line for line in err if line.startswith("blockray: error:")]     # (B = 14 warns of cornell)
    assert code == 2 and len(errors) == 1 and "needs a board that makes its rays" in errors[0], err
    assert "IDENTIFY version 5" in errors[0] and "not ulx3s" in errors[0], err


def test_ulx3s_board_takes_its_cell_from_identify(lean_ulx3s_on_a_pty):
    """A lean bitstream says its cell in IDENTIFY: ``--board ulx3s`` without ``--cell`` counts the
    lean board's cycles, and the render equals ``--board model --cell lean``'s, cycles included."""
    name, _ = lean_ulx3s_on_a_pty
    scene = load_scene("cornell")
    run = dict(rows=2, cols=2, boards=1, samples=4, max_shots=2, voxels=4)
    options = RenderOptions.of(backend="ulx3s", port=name, **run)
    with build_board(options.board) as board:
        real = render(scene, board, options)
        assert board.cell == Cell("lean").at(14)
    assert real.report["cell"] == "lean d9w9"
    model = render(scene, backend="model", bits=14, cell=Cell("lean"), **run)
    assert np.array_equal(real.radiosity, model.radiosity)
    for key in ("tests", "tests_issued", "board_cycles", "board_cycles_per_board", "rays", "blocks"):
        assert real.report[key] == model.report[key], key


def test_ulx3s_board_refuses_another_cell(ulx3s_on_a_pty, capsys):
    """An exact bitstream asked for the lean cell is refused before anything is uploaded, with
    the cell named as IDENTIFY gave it."""
    name, _ = ulx3s_on_a_pty
    code = main(["render", "cornell", "--board", "ulx3s", "--port", name, "--boards", "1", "--rows", "2",
                 "--cols", "2", "--cell", "lean", "--max-shots", "1", "--quiet"])
    err = capsys.readouterr().err.strip().splitlines()
    errors = [line for line in err if line.startswith("blockray: error:")]     # (B = 14 warns of cornell)
    assert code == 2 and errors == ["blockray: error: board 0 was built for another configuration: "
                                    "cell exact (host lean d9w9; --cell)"], err
