"""The route polyline of a world: sampling, simplification and scanner stations along it."""

from __future__ import annotations

import math

import numpy as np


def _sample_polyline(route: np.ndarray, step: float) -> np.ndarray:
    """Points (M, 3) along a polyline (K, 3), at most ``step`` apart, including the waypoints."""
    pieces = []
    for start, end in zip(route[:-1], route[1:], strict=True):
        count = max(1, int(math.ceil(np.linalg.norm(end - start) / step)))
        t = np.arange(count)[:, None] / count
        pieces.append(start + t * (end - start))
    pieces.append(route[-1:])
    return np.concatenate(pieces)


def _simplify_route(points: list[tuple[float, float, float]]) -> np.ndarray:
    """(K, 3) route without repeated waypoints or waypoints on a straight line."""
    route = [np.asarray(points[0], float)]
    for p in points[1:]:
        p = np.asarray(p, float)
        if np.linalg.norm(p - route[-1]) > 1e-6:
            route.append(p)
    keep = [route[0]]
    for k in range(1, len(route) - 1):
        a, b = route[k] - keep[-1], route[k + 1] - route[k]
        if (
            np.linalg.norm(np.cross(a, b)) > 1e-9 * np.linalg.norm(a) * np.linalg.norm(b)
            or a @ b < 0
        ):
            keep.append(route[k])
    keep.append(route[-1])
    return np.asarray(keep, dtype=np.float64)


def _tls_stations(route: np.ndarray, spacing: float, height: float) -> np.ndarray:
    """(S, 3) scanner positions ``height`` above level parts of the route, ~``spacing`` apart."""
    samples = _sample_polyline(route, 0.25)
    arc = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(samples, axis=0), axis=1))])
    count = max(2, int(arc[-1] // spacing))
    targets = (np.arange(count) + 0.5) * arc[-1] / count
    index = np.searchsorted(arc, targets).clip(0, len(samples) - 1)
    # Level parts only: the waypoints on either side have the same height.
    segment = np.searchsorted(np.cumsum(np.linalg.norm(np.diff(route, axis=0), axis=1)), targets)
    segment = segment.clip(0, len(route) - 2)
    level = np.abs(route[segment, 2] - route[segment + 1, 2]) < 1e-9
    stations = samples[index[level]] + np.array([0.0, 0.0, height])
    return stations.astype(np.float64)
