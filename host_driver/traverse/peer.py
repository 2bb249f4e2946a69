"""Embree (embreex, the ``[bench]`` extra) answering the board's occlusion queries: the CPU peer the
boards are compared with (benchmarks/bench_host.py, ``blockray sweep``'s projected Embree time).

Importing this module raises ImportError without embreex."""

import time

import numpy as np
from embreex import rtcore_scene as rtcs
from embreex.mesh_construction import TriangleMesh

__all__ = ["embree_occluded"]


def embree_occluded(scene, P, Q, eps=1e-4):
    """Is each segment P -> Q blocked (its ends trimmed by ``eps`` of its length)?
    -> (hit (n,) bool, wall s, CPU s of the queries, CPU s of building the BVH)."""
    c0 = time.process_time()
    es = rtcs.EmbreeScene()
    TriangleMesh(es, scene.patch_vertices.astype(np.float32))
    d = (Q - P).astype(np.float32)
    origin = (P + eps * (Q - P)).astype(np.float32)
    dist = np.full(len(P), 1 - 2 * eps, np.float32)
    es.run(origin[:1], d[:1], dists=dist[:1], query="OCCLUDED")     # BVH built at the first query
    build = time.process_time() - c0
    t1, c1 = time.perf_counter(), time.process_time()
    hit = es.run(origin, d, dists=dist, query="OCCLUDED") >= 0
    return hit, time.perf_counter() - t1, time.process_time() - c1, build
