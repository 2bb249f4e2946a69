"""Resources released on every path: a board render() builds is closed when the render succeeds,
fails or is interrupted; a board the CLI builds (--link-faults) likewise."""

import pytest

from blockray.host_driver.cli import main
from blockray.errors import SolveError
from blockray.host_driver.board import backends
from blockray.host_driver.render import render as renders
from blockray.host_driver.scene.builtin import load_scene


@pytest.fixture
def closes(monkeypatch):
    """The boards built during the test, each with the number of times it was closed."""
    built = []
    make = backends.build_board

    def counting(*args, **kw):
        board = make(*args, **kw)
        close = board.close
        entry = {"board": board, "closed": 0}

        def counted():
            entry["closed"] += 1
            close()
        board.close = counted
        built.append(entry)
        return board
    monkeypatch.setattr(renders, "build_board", counting)
    monkeypatch.setattr(backends, "build_board", counting)
    return built


@pytest.mark.parametrize("ending", ["success", "error", "interrupt"])
def test_render_closes_its_board(monkeypatch, closes, ending):
    scene = load_scene("cornell", max_edge=1000)
    fraction, calls = renders.visible_fraction, [0]

    def failing(*args, **kw):
        calls[0] += 1
        if calls[0] == 3 and ending != "success":
            raise SolveError("a failed board") if ending == "error" else KeyboardInterrupt
        return fraction(*args, **kw)
    monkeypatch.setattr(renders, "visible_fraction", failing)
    if ending == "success":
        renders.render(scene, backend="model-link", max_shots=4, samples=2)
    else:
        with pytest.raises(SolveError if ending == "error" else KeyboardInterrupt):
            renders.render(scene, backend="model-link", max_shots=4, samples=2)
    assert len(closes) == 1 and closes[0]["closed"] >= 1
    assert closes[0]["board"].transports == []          # its links, open since load(), were closed


def test_cli_closes_the_board_it_built(monkeypatch, closes, capsys):
    def failing(*args, **kw):
        raise SolveError("a failed board")
    monkeypatch.setattr(renders, "visible_fraction", failing)
    code = main(["render", "cornell", "--max-edge", "1000", "--board", "model-link", "--link-faults", "0",
                 "--max-shots", "2", "--samples", "2", "--quiet"])
    assert code == 2 and "a failed board" in capsys.readouterr().err
    assert len(closes) == 1 and closes[0]["board"].transports == []
