"""The weights of the visibility estimate's rays: the point factor from each sample point of a
shooter to a receiver, where the sample is in front of the receiver's plane (numba); and the
exact in-front tests of ray end points. :mod:`~blockray.host_driver.traverse.visibility`
averages a pair's clear rays with them.
"""

import numpy as np
from numba import njit, prange

from ... import threads as _threads  # (also chooses the threading layer before any kernel runs)
from ...exact_float import _plane_sign, plane_signs
from .point_factor import _lambert_normal

__all__ = ["centroid_in_front", "samples_in_front", "sample_weights", "weight_points",
           "pair_sample_weights"]

_ONES = np.ones(3, dtype=np.int64)


def centroid_in_front(scene, i, receivers):
    """bool (len(receivers),): receiver j's centroid (its ray end point) strictly in front of i's
    plane. Where it is not, rays from i to j's centroid say nothing about the light i sends to the
    part of j in front of it; the render casts the reverse rays instead."""
    return _centroids_in_front(scene.patch_vertices, int(i), np.asarray(receivers, dtype=np.int64))


@njit(cache=True)
def _centroids_in_front(V, i, receivers):
    out = np.empty(len(receivers), dtype=np.bool_)
    for m in range(len(receivers)):
        out[m] = _plane_sign(V[i], V[receivers[m]], _ONES) > 0
    return out


def samples_in_front(scene, samples, i, receivers):
    """bool (len(receivers), K sets): sample point k of shooter i strictly in front of receiver j's
    plane (exact signs). Only those rays carry light from i to j."""
    V = scene.patch_vertices
    receivers = np.asarray(receivers, dtype=np.int64)
    K = samples.per_patch                    # every set's points, when the patch has several
    tri = np.repeat(V[receivers], K, axis=0)
    pts = np.broadcast_to(V[i], (len(tri), 3, 3))
    w = np.tile(samples.weights_of([i])[0], (len(receivers), 1))
    return (plane_signs(tri, pts, w) > 0).reshape(len(receivers), K)


def sample_weights(scene, samples, i, receivers):
    """(len(receivers), K): each ray's share of the light shooter i sends to receiver j: the
    point factor from sample point k of i (normal of i) to triangle j, where the sample is
    strictly in front of j's plane (:func:`samples_in_front`), else 0. Their weighted mean of
    clear rays estimates the kernel-weighted visible fraction (a plain mean weighs a sample
    near j like one far from it)."""
    receivers = np.asarray(receivers, dtype=np.int64)
    return pair_sample_weights(scene, samples, np.full(len(receivers), i), receivers)


def weight_points(scene, samples, patches=None):
    """(len(patches), K, 3): the float sample points of each patch (default: all) as
    :func:`pair_sample_weights` weighs them, each triangle's computed alone (so the same bits
    whichever patches are asked for together)."""
    V = scene.patch_vertices
    patches = range(scene.patches) if patches is None else patches
    points = [samples.points(V[j][None], [j])[0] for j in patches]
    return np.stack(points) if points else np.zeros((0, samples.per_patch, 3))


def pair_sample_weights(scene, samples, shooters, receivers, points=None):
    """:func:`sample_weights` of many (shooter, receiver) pairs in one call: row m is the weight row
    of the pair (shooters[m], receivers[m]), the same arithmetic row by row, so the same bits however
    the pairs are batched. For the reverse rays of a shooter's straddling receivers. ``points``:
    :func:`weight_points` of every patch, if the caller keeps them (else computed for these
    shooters)."""
    shooters = np.asarray(shooters, dtype=np.int64)
    receivers = np.asarray(receivers, dtype=np.int64)
    if len(shooters) == 0:
        return np.zeros((0, samples.per_patch))
    if points is None:
        unique, which = np.unique(shooters, return_inverse=True)
        points, shooters = weight_points(scene, samples, unique), which.reshape(-1).astype(np.int64)
        normals = np.ascontiguousarray(scene.normals[unique], dtype=np.float64)
        return _sample_weights(scene.patch_vertices, normals, points, _weights_of(samples, unique), shooters,
                               receivers, unique)
    every = np.arange(scene.patches)
    return _sample_weights(scene.patch_vertices, np.ascontiguousarray(scene.normals, dtype=np.float64), points,
                           _weights_of(samples, every), shooters, receivers, every)


def _weights_of(samples, patches):
    """(len(patches), K, 3) sample weights, one row per entry of ``points``; the fixed pattern's
    as one row (index 0 for every patch: the kernels index ``weights[s % len(weights)]``)."""
    return (np.ascontiguousarray(samples.weights_of(patches)) if samples.drawn
            else np.ascontiguousarray(samples.weights)[None])


@njit(cache=True)
def _weight_row(V, normals, points, weights, s, i, j, out, poly):
    """out[:]: for shooter i (its points and normal at index s), receiver j, the point factor of
    each sample strictly in front of j's plane, else 0."""
    w = weights[s % len(weights)]
    for k in range(w.shape[0]):
        if _plane_sign(V[j], V[i], w[k]) > 0:
            out[k] = _lambert_normal(points[s], k, normals, s, V[j], poly)


def _weights(V, normals, points, weights, shooters, receivers, patch, out):
    for m in prange(len(shooters)):
        _weight_row(V, normals, points, weights, shooters[m], patch[shooters[m]], receivers[m], out[m],
                    np.empty((4, 3)))


_weights_par, _weights_ser = _threads.twins(_weights)


def _sample_weights(V, normals, points, weights, shooters, receivers, patch):
    """Row m: the weight row of shooter ``patch[shooters[m]]`` (its points and normal at index
    shooters[m]) and receiver receivers[m]; rows on the thread pool when there are enough rays
    (each row its own, so the same bits on any number of threads)."""
    out = np.zeros((len(shooters), weights.shape[1]))
    run = _weights_par if _threads.parallel(out.size) else _weights_ser
    run(V, normals, points, weights, shooters, receivers, patch, out)
    return out
