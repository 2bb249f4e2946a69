"""Checkpoints and resume (host_driver/render/checkpoint.py): a render killed (SIGKILL) at a seeded random
step, or in the middle of writing its checkpoint, and resumed, writes the same CSV and image as an
uninterrupted render, bit for bit, with each solver; a checkpoint of another render is refused."""

import json
import random
import signal
import subprocess
import sys
import textwrap

import numpy as np
import pytest

from blockray.host_driver.cli import main
from blockray.host_driver.radiosity import solver as solvers
from blockray.host_driver.scene.builtin import load_scene
from blockray.host_driver.render.checkpoint import FILE

SCENE = ["cornell", "--max-edge", "300", "--samples", "2", "--size", "32", "--quiet"]
#: per solver: its options and the checkpoints (steps) an uninterrupted render writes
SOLVERS = {"progressive": (["--max-shots", "12"], 12), "jacobi": (["--tolerance", "1e-4"], 14),
           "gauss-seidel": (["--tolerance", "1e-4"], 8)}

#: the CLI with a checkpoint after every step, killed by SIGKILL at the KILL-th checkpoint: before
#: it is written (the last step's work is lost) or after its temporary is written and fsynced, before
#: the rename ("write")
_KILLED = textwrap.dedent("""
    import os, signal, sys
    from blockray import atomic
    from blockray.host_driver.cli import main
    from blockray.host_driver.render import checkpoint
    kill, where = int(sys.argv[1]), sys.argv[2]
    checkpoint.INTERVAL = 0
    save, fsync, count = checkpoint.Checkpoint.save, atomic._fsync, [0]

    def counted(self, state, **kw):
        count[0] += 1
        if count[0] == kill and where == "before":
            os.kill(os.getpid(), signal.SIGKILL)
        return save(self, state, **kw)

    def synced(f):
        fsync(f)
        if count[0] == kill:
            os.kill(os.getpid(), signal.SIGKILL)
    checkpoint.Checkpoint.save = counted
    atomic._fsync = synced
    sys.exit(main(sys.argv[3:]))
""")


def _outputs(folder, tag):
    return ["--patches", str(folder / f"{tag}.csv"), "--image", str(folder / f"{tag}.png")]


@pytest.mark.parametrize("solver", list(SOLVERS))
def test_killed_and_resumed_equals_uninterrupted(tmp_path, solver):
    seed = {"progressive": 1, "jacobi": 2, "gauss-seidel": 3}[solver]
    rng = random.Random(seed)
    options, steps = SOLVERS[solver]
    kill, where = rng.randint(2, steps - 1), rng.choice(["before", "write"])
    print(f"seed={seed} kill at checkpoint {kill} ({where})")
    argv = ["render", *SCENE, "--solver", solver, *options]
    assert main(argv + _outputs(tmp_path, "whole") + ["--report", str(tmp_path / "whole.json")]) == 0
    folder = tmp_path / "ck"
    done = subprocess.run([sys.executable, "-c", _KILLED, str(kill), where, *argv, "--checkpoint", str(folder),
                           *_outputs(tmp_path, "killed")], capture_output=True, text=True, timeout=300)
    assert done.returncode == -signal.SIGKILL, done.stderr
    assert not (tmp_path / "killed.csv").exists()
    assert main(argv + ["--resume", str(folder), "--report", str(tmp_path / "r.json")]
                + _outputs(tmp_path, "resumed")) == 0
    for ext in ("csv", "png"):
        assert (tmp_path / f"resumed.{ext}").read_bytes() == (tmp_path / f"whole.{ext}").read_bytes(), ext
    # it did continue, from the last checkpoint completed before the kill
    report = json.loads((tmp_path / "r.json").read_text())
    step = "shots" if solver == "progressive" else "sweeps"
    assert report["resumed_from"] == {"shots": 0, "sweeps": 0, step: kill - 1}, report["resumed_from"]
    whole = json.loads((tmp_path / "whole.json").read_text())
    assert (report["shots"], report["iterations"], report["residual"], report["visible_row_sum"]) == \
        (whole["shots"], whole["iterations"], whole["residual"], whole["visible_row_sum"])
    if solver == "progressive":         # only the shots after the checkpoint cast their rays again
        assert report["rays"] < whole["rays"], (report["rays"], whole["rays"])


def test_a_checkpoint_of_another_render_is_refused(tmp_path, capsys):
    folder = tmp_path / "ck"
    argv = ["render", *SCENE, "--max-shots", "3"]
    code = main(argv + ["--resume", str(folder)])
    err = capsys.readouterr().err
    assert code == 2 and err.strip() == f"blockray: error: --resume {folder}: no checkpoint there ({FILE}); a " \
                                        f"render writes one with --checkpoint", err
    from blockray.host_driver.render import checkpoint
    interval, checkpoint.INTERVAL = checkpoint.INTERVAL, 0
    try:
        assert main(argv + ["--checkpoint", str(folder)]) == 0
    finally:
        checkpoint.INTERVAL = interval
    assert (folder / FILE).exists()
    for other, needle in [(["--samples", "3"], "made with samples 2, this render has 3"),
                          (["--max-shots", "4"], "made with max_shots 3, this render has 4"),
                          (["--board", "golden"], "made with board 'model', this render has 'golden'"),
                          (["--max-edge", "400"], "the checkpoint's scene 'cornell' has other contents")]:
        code = main(argv + other + ["--resume", str(folder)])
        err = capsys.readouterr().err
        assert code == 2 and needle in err and len(err.strip().splitlines()) == 1, err
    code = main(["render", "room", "--max-edge", "1000", "--max-shots", "3", "--quiet", "--resume", str(folder)])
    err = capsys.readouterr().err
    assert code == 2 and "the checkpoint is of scene 'cornell', not 'room'" in err, err
    (folder / FILE).write_bytes(b"not a checkpoint")
    code = main(argv + ["--resume", str(folder)])
    err = capsys.readouterr().err
    assert code == 2 and f"{FILE} is not a blockray checkpoint" in err and "Traceback" not in err, err


@pytest.mark.parametrize("solver", ["progressive", "jacobi", "gauss-seidel"])
def test_solver_state_resumes_bit_for_bit(solver):
    """The solvers alone: stopped after every possible step and resumed from its saved state."""
    scene = load_scene("cornell", max_edge=400)
    rng = np.random.default_rng(5)
    print("seed=5")
    F = rng.random((scene.patches, scene.patches)) * 0.9 / scene.patches
    np.fill_diagonal(F, 0)
    states = []

    def solve(resume=None, stop=None):
        def checkpoint(state):
            states.append(state)
            if stop is not None and len(states) == stop:
                raise KeyboardInterrupt
        if solver == "progressive":
            return solvers.progressive_refinement(scene, lambda i: F[:, i], tolerance=1e-6, max_shots=40,
                                                  checkpoint=checkpoint, resume=resume)
        gather = solvers.jacobi if solver == "jacobi" else solvers.gauss_seidel
        return gather(scene, F, tolerance=1e-9, checkpoint=checkpoint, resume=resume)
    whole = solve()
    steps = len(states)
    assert steps > 3
    for stop in range(1, steps):
        states.clear()
        with pytest.raises(KeyboardInterrupt):
            solve(stop=stop)
        state = states[-1]
        states.clear()
        again = solve(resume=state)
        assert len(states) == steps - stop            # it went on from the state, not from the start
        np.testing.assert_array_equal(again.B, whole.B)
        assert (again.shots, again.iterations, again.history) == (whole.shots, whole.iterations, whole.history)


def test_hierarchical_killed_and_resumed_equals_uninterrupted(tmp_path, capsys):
    """--solver hierarchical, killed (SIGKILL) at a seeded random round's checkpoint and resumed:
    the same leaves' CSV and image, bit for bit, as the render never stopped, from the round the
    checkpoint had reached, casting only the later rounds' rays."""
    seed = 4
    argv = ["render", "cornell", "--max-edge", "1e9", "--samples", "2", "--size", "32", "--quiet",
            "--solver", "hierarchical", "--epsilon", "3e-3"]
    assert main(argv + _outputs(tmp_path, "whole") + ["--report", str(tmp_path / "whole.json")]) == 0
    whole = json.loads((tmp_path / "whole.json").read_text())
    rounds = whole["refinement_rounds"]                     # checkpoints written: one per round's solve
    rng = random.Random(seed)
    kill, where = rng.randint(2, rounds + 1), rng.choice(["before", "write"])
    print(f"seed={seed} kill at checkpoint {kill} of {rounds + 1} ({where})")
    folder = tmp_path / "ck"
    done = subprocess.run([sys.executable, "-c", _KILLED, str(kill), where, *argv, "--checkpoint", str(folder),
                           *_outputs(tmp_path, "killed")], capture_output=True, text=True, timeout=300)
    assert done.returncode == -signal.SIGKILL, done.stderr
    assert main(argv + ["--resume", str(folder), "--report", str(tmp_path / "r.json")] + _outputs(tmp_path, "resumed")) == 0
    for ext in ("csv", "png"):
        assert (tmp_path / f"resumed.{ext}").read_bytes() == (tmp_path / f"whole.{ext}").read_bytes(), ext
    report = json.loads((tmp_path / "r.json").read_text())
    # checkpoint k holds round k - 1's solve (round 0: the input triangles); the k-th never completed
    assert report["resumed_from"]["rounds"] == kill - 2, report["resumed_from"]
    keys = ("refinement_rounds", "links", "cluster_links", "leaves", "iterations")
    assert whole["cluster_links"] > 0 and [report[k] for k in keys] == [whole[k] for k in keys]
    assert report["rays"] < whole["rays"]
    other = [a if a != "3e-3" else "1e-2" for a in argv]
    capsys.readouterr()
    assert main(other + ["--resume", str(folder)]) == 2                # another epsilon: refused, exit 2
    assert "made with epsilon 0.003, this render has 0.01" in capsys.readouterr().err
