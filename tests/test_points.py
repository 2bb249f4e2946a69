"""The point unit (rtl/points.py PointUnit, its model sim/points.py point_of) against the host's
integers: the sample points and centroids ``quantise`` computes for cornell (``SampleScheme.points_int``
/ ``centroids_int``, numpy integer division: no code shared with the unit's multiply by the
inverse), with an odd denominator (K = 8: D = 21) and an even one (end lattice 2: D = 42). The
gateware in the Amaranth simulator equals the model point for point and cycle for cycle (random
idle and back-pressure, seeded)."""

import random

import numpy as np
import pytest

from blockray.errors import ParameterError
from blockray.fixedpoint import quantise
from blockray.points import POINT_LATENCY, PointArithmetic
from blockray.rtl.points import PointUnit, point_job_layout
from blockray.samples import SampleScheme
from blockray.sim.points import point_of
from stream_bench import drive_streams

BITS = 16


@pytest.fixture(scope="module", params=[1, 2], ids=["D21", "D42"])
def cornell(request):
    """(scheme, quantised cornell) at B = 16 with 8 samples and end lattice 1 or 2."""
    from blockray.host_driver.scene.builtin import load_scene
    scheme = SampleScheme(8, end_lattice=request.param)
    return scheme, quantise(load_scene("cornell"), scheme, BITS)


def _jobs(scheme, q, patches):
    """(patch, weights, the host's point) for every sample and the centroid of ``patches``."""
    out = []
    for n in patches:
        for k, w in enumerate(scheme.weights):
            out.append((n, tuple(int(x) for x in w), tuple(int(x) for x in q.shooters[n, k])))
        out.append((n, tuple(int(x) for x in scheme.centroid_weights), tuple(int(x) for x in q.receivers[n])))
    return out


def test_model_equals_the_hosts_integers(cornell):
    scheme, q = cornell
    arith = PointArithmetic(BITS, scheme.denominator)
    assert arith.shift == scheme.end_lattice.bit_length() - 1
    V = q.vertices.tolist()
    for n, w, host in _jobs(scheme, q, range(len(V))):
        assert point_of(V[n], w, arith) == host, (n, w)


def _record(q, n):
    v, normal = q.vertices[n], q.normals[n]
    point = [{"x": int(p[0]), "y": int(p[1]), "z": int(p[2])} for p in v]
    return {"v0": point[0], "v1": point[1], "v2": point[2],
            "normal": {"x": int(normal[0]), "y": int(normal[1]), "z": int(normal[2])}}


def test_gateware_equals_the_model_cycle_for_cycle(cornell, rng_seed):
    scheme, q = cornell
    rng = random.Random(rng_seed)
    jobs = _jobs(scheme, q, rng.sample(range(len(q.vertices)), 6))
    dut = PointUnit(bits=BITS, denominator=scheme.denominator)
    layout = point_job_layout(dut.arithmetic)
    V = q.vertices.tolist()
    got, state = [], {"taken": None, "first_valid": None}

    def step(ctx, cycle, job):
        if ctx.get(dut.points.valid):
            taken = state["taken"]
            assert taken is not None
            if state["first_valid"] is None:
                state["first_valid"] = cycle
                assert cycle - taken[0] == POINT_LATENCY                    # the model's cycle contract
            if ctx.get(dut.points.ready):
                p = ctx.get(dut.points.payload)
                got.append(taken[1:] + ((p.x, p.y, p.z),))
                state["taken"] = state["first_valid"] = None
        if job is not None:
            assert state["taken"] is None                                   # one job at a time
            state["taken"] = (cycle,) + job

    drive_streams(dut, dut.jobs, dut.points, jobs, rng, step, until=lambda: len(got) == len(jobs),
                  payload=lambda job: layout.const({"patch": _record(q, job[0]), "weights": list(job[1])}))
    for n, w, host, point in got:
        assert point == host == point_of(V[n], w, dut.arithmetic), (n, w)


@pytest.mark.parametrize("kw", [{"bits": 3, "denominator": 21}, {"bits": 16, "denominator": 0},
                                {"bits": 16, "denominator": 2.5}])
def test_bad_parameters_are_one_error(kw):
    """PointUnit's parameters, checked by the PointArithmetic it builds first."""
    with pytest.raises(ParameterError):
        PointArithmetic(**kw)
