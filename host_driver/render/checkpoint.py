"""Checkpoints of a long render (``render --checkpoint DIR``) and their resumption (``--resume DIR``).

A checkpoint is one file, ``DIR/checkpoint.npz`` (numpy's ``savez``: no pickles), replaced
atomically (:mod:`blockray.atomic`) at most every :data:`INTERVAL` seconds while the solve runs:

- progressive refinement: after a shot, B, the unshot radiosity U and its per-patch energy, the
  shots done, the unshot-energy history, the largest row sum and gain checked, and the shooters
  whose columns of visible factors the render had cached (their identity; a column is
  recomputed, bit for bit, when a resumed render needs it again);
- Jacobi and Gauss-Seidel: after a sweep, the iterate to sweep next and the residual history.
- hierarchical: after each refinement round's solve, the elements (their input triangle, node,
  level, parent and first child), the links (ends, unoccluded factor, visible fraction, partial
  flag), every element's B, the rounds and sweeps done and that solve's residual history and
  balance; a resumed render refines from there and casts only the rays of later rounds.
  The form factors are not saved: a resumed gathering render casts its rays again (on one set or
  on the cluster's sets) and then continues from the saved sweep.

With it, ``meta``: the format, the scene's name and :func:`scene_hash` (a SHA-256 of its
geometry, materials and groups), and the options the radiosity depends on. ``--resume DIR``
refuses (:class:`~blockray.errors.ParameterError`, exit 2) a checkpoint of another scene, of
other contents or of other options, naming what differs. As every step is deterministic, a
resumed render writes the same radiosity, image and CSV, bit for bit, as one never stopped; its
report counts the work of the resumed run (rays, tests, seconds) and ``resumed_from``.
"""

import hashlib
import json
import os
import time

import numpy as np

from ...atomic import write_file
from ...errors import ParameterError, ResourceError, option, printable

__all__ = ["Checkpoint", "scene_hash", "FILE", "INTERVAL"]

#: the checkpoint's file name in its folder
FILE = "checkpoint.npz"
#: seconds between two checkpoints of a running solve (the first: the first step this long after
#: the solve starts)
INTERVAL = 30.0
FORMAT = 2
_STATE = ("B", "U", "energy", "history", "row_sums", "columns")
#: a hierarchical render's arrays (host_driver/render/hierarchical.py, ``solve_state``)
HIERARCHICAL = ("patch", "node", "level", "parent", "child", "recv", "src", "F", "vis", "partial", "B", "history",
                "cluster_R", "cluster_S", "cluster_vis", "cluster_partial", "cluster_rkey", "cluster_rvis", "u", "w")


def scene_hash(scene):
    """SHA-256 (hex) of the scene's vertices, triangles, reflectance, emission and groups."""
    h = hashlib.sha256()
    for a in (scene.vertices, scene.triangles, scene.reflectance, scene.emission, scene.group):
        a = np.ascontiguousarray(a)
        h.update(f"{a.dtype.str}{a.shape}".encode())
        h.update(a.tobytes())
    h.update(json.dumps(list(scene.group_names)).encode())
    return h.hexdigest()


class Checkpoint:
    """Where a render saves its solve (``save_to``, a folder, or None) and what it resumes
    (``resume_from``, a folder, or None). :meth:`bind` names the render; :meth:`save` is the
    solvers' ``checkpoint`` callback."""

    def __init__(self, save_to=None, resume_from=None, *, interval=None):
        self.save_to, self.resume_from = save_to, resume_from
        self.interval = INTERVAL if interval is None else interval
        self.meta = None
        self.columns = None          # () -> the cached shooters, given by the render
        self._last = None

    def bind(self, scene, options):
        """Name the render (its scene and ``options``, a dict of plain values); returns the state to
        resume (None without ``resume_from``). A checkpoint of another render raises ParameterError."""
        self.meta = {"format": FORMAT, "scene": scene.name, "scene_hash": scene_hash(scene),
                     "options": json.loads(json.dumps(options))}
        self._last = time.monotonic()
        if self.resume_from is None:
            return None
        return self._load()

    def _path(self, folder):
        return os.path.join(os.fspath(folder), FILE)

    def _load(self):
        path = self._path(self.resume_from)
        shown = f"{option('resume')} {printable(self.resume_from, 200)}"
        try:
            with np.load(path, allow_pickle=False) as data:
                saved = {k: data[k] for k in data.files}
            meta = json.loads(str(saved.pop("meta")))
        except FileNotFoundError:
            raise ParameterError(f"{shown}: no checkpoint there ({FILE}); a render writes one with "
                                 f"{option('checkpoint')}", parameter="resume") from None
        except (OSError, ValueError, KeyError) as e:
            raise ParameterError(f"{shown}: {FILE} is not a blockray checkpoint ({printable(e, 200)})",
                                 parameter="resume") from None
        if meta.get("format") != FORMAT:
            raise ParameterError(f"{shown}: checkpoint format {meta.get('format')!r}, this blockray reads {FORMAT}",
                                 parameter="resume")
        if meta.get("scene") != self.meta["scene"]:
            raise ParameterError(f"{shown}: the checkpoint is of scene {printable(meta.get('scene'), 100)!r}, "
                                 f"not {printable(self.meta['scene'], 100)!r}", parameter="resume")
        if meta.get("scene_hash") != self.meta["scene_hash"]:
            raise ParameterError(f"{shown}: the checkpoint's scene {printable(meta['scene'], 100)!r} has other "
                                 f"contents ({option('max_edge')}, {option('contact')} or the file changed)", parameter="resume")
        theirs, ours = meta.get("options", {}), self.meta["options"]
        for key in sorted(set(theirs) | set(ours)):
            if theirs.get(key) != ours.get(key):
                raise ParameterError(f"{shown}: the checkpoint was made with {key} {theirs.get(key)!r}, this "
                                     f"render has {ours.get(key)!r}", parameter="resume")
        if str(saved["solver"]) == "hierarchical":
            return {"solver": "hierarchical", "shots": 0, "iterations": int(saved["iterations"]),
                    "rounds": int(saved["rounds"]), "residual": float(saved["residual"]),
                    "balance": json.loads(str(saved["balance"])), "arrays": {k: saved[k] for k in HIERARCHICAL}}
        state = {k: saved[k] for k in _STATE}
        state.update(solver=str(saved["solver"]), shots=int(saved["shots"]), iterations=int(saved["iterations"]))
        return state

    def save(self, state, *, force=False):
        """Write ``state`` (:func:`~blockray.host_driver.radiosity.solver.solve_state`) if :data:`INTERVAL`
        seconds have passed since the last write (or ``force``)."""
        if self.save_to is None or (not force and time.monotonic() - self._last < self.interval):
            return
        if state["solver"] == "hierarchical":
            arrays = dict(state["arrays"], rounds=np.array(state["rounds"]), residual=np.array(state["residual"]),
                          balance=np.array(json.dumps(state["balance"])))
        else:
            columns = np.array(sorted(self.columns()) if self.columns is not None else [], dtype=np.int64)
            arrays = {k: np.asarray(state[k]) for k in _STATE if k != "columns"}
            arrays["columns"] = columns
        arrays.update(solver=np.array(state["solver"]), shots=np.array(state["shots"]),
                      iterations=np.array(state["iterations"]), meta=np.array(json.dumps(self.meta)))
        try:
            os.makedirs(self.save_to, exist_ok=True)
        except OSError as e:
            raise ResourceError(f"{option('checkpoint')} {printable(self.save_to, 200)}: cannot create it: "
                                f"{e.strerror or e}") from None
        write_file(self._path(self.save_to), "--checkpoint", lambda f: np.savez(f, **arrays), binary=True)
        self._last = time.monotonic()
