"""Triangle-mesh primitives (numpy arrays) and a builder that tags triangles with material + object ids."""

from __future__ import annotations

import numpy as np

_BOX_CORNERS = np.array([[-1, -1, -1], [1, -1, -1], [1, 1, -1], [-1, 1, -1],
                         [-1, -1, 1], [1, -1, 1], [1, 1, 1], [-1, 1, 1]], np.float64)
_BOX_FACES = np.array([[0, 2, 1], [0, 3, 2], [4, 5, 6], [4, 6, 7], [0, 1, 5], [0, 5, 4],
                       [2, 3, 7], [2, 7, 6], [1, 2, 6], [1, 6, 5], [0, 4, 7], [0, 7, 3]], np.int64)


def box(center, axes: np.ndarray, half: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Oriented box: ``axes`` 3×3 with unit axis vectors as columns, ``half`` half-extents (m)."""
    V = np.asarray(center, np.float64) + (_BOX_CORNERS * np.asarray(half, np.float64)) @ np.asarray(axes).T
    return V, _BOX_FACES.copy()


def cylinder(base, axis, radius: float, height: float, segments: int = 8, cap: bool = True):
    """Cylinder from ``base`` along unit ``axis`` (metres)."""
    axis = np.asarray(axis, np.float64)
    a = np.cross(axis, [1.0, 0, 0] if abs(axis[0]) < 0.9 else [0, 0, 1.0])
    a /= np.linalg.norm(a)
    b = np.cross(axis, a)
    ang = np.linspace(0, 2 * np.pi, segments, endpoint=False)
    ring = radius * (np.cos(ang)[:, None] * a + np.sin(ang)[:, None] * b)
    base = np.asarray(base, np.float64)
    V = np.concatenate([base + ring, base + height * axis + ring, [base + height * axis]])
    i = np.arange(segments)
    j = (i + 1) % segments
    F = np.concatenate([np.stack([i, j, j + segments], 1), np.stack([i, j + segments, i + segments], 1)])
    if cap:
        F = np.concatenate([F, np.stack([i + segments, j + segments, np.full(segments, 2 * segments)], 1)])
    return V, F


def _icosahedron():
    t = (1 + 5 ** 0.5) / 2
    V = np.array([[-1, t, 0], [1, t, 0], [-1, -t, 0], [1, -t, 0], [0, -1, t], [0, 1, t], [0, -1, -t], [0, 1, -t],
                  [t, 0, -1], [t, 0, 1], [-t, 0, -1], [-t, 0, 1]], np.float64)
    F = np.array([[0, 11, 5], [0, 5, 1], [0, 1, 7], [0, 7, 10], [0, 10, 11], [1, 5, 9], [5, 11, 4], [11, 10, 2],
                  [10, 7, 6], [7, 1, 8], [3, 9, 4], [3, 4, 2], [3, 2, 6], [3, 6, 8], [3, 8, 9], [4, 9, 5],
                  [2, 4, 11], [6, 2, 10], [8, 6, 7], [9, 8, 1]])
    return V / np.linalg.norm(V, axis=1, keepdims=True), F


def _subdivide(V, F):
    edges = {}
    V = list(V)
    out = []

    def mid(a, b):
        key = (min(a, b), max(a, b))
        if key not in edges:
            m = (V[a] + V[b]) / 2
            V.append(m / np.linalg.norm(m))
            edges[key] = len(V) - 1
        return edges[key]

    for a, b, c in F:
        ab, bc, ca = mid(a, b), mid(b, c), mid(c, a)
        out += [[a, ab, ca], [b, bc, ab], [c, ca, bc], [ab, bc, ca]]
    return np.array(V), np.array(out)


_ICO1 = _subdivide(*_icosahedron())


def blob(center, radii, rng: np.random.Generator, jitter: float = 0.15):
    """Lumpy ellipsoid (80 triangles): tree crowns, bushes."""
    V, F = _ICO1
    r = 1.0 + jitter * (rng.random(len(V)) * 2 - 1)
    return np.asarray(center) + V * r[:, None] * np.asarray(radii), F.copy()


class MeshBuilder:
    """Accumulates triangles with a material id and an object id per triangle."""

    def __init__(self):
        self.V, self.F, self.mat, self.obj = [], [], [], []
        self.nv = 0

    def add(self, V: np.ndarray, F: np.ndarray, material: int, obj: int = -1) -> None:
        self.V.append(np.asarray(V, np.float64))
        self.F.append(np.asarray(F, np.int64) + self.nv)
        self.mat.append(np.full(len(F), material, np.uint8))
        self.obj.append(np.full(len(F), obj, np.int32))
        self.nv += len(V)

    def add_tagged(self, V, F, materials: np.ndarray, obj: int = -1) -> None:
        self.V.append(np.asarray(V, np.float64))
        self.F.append(np.asarray(F, np.int64) + self.nv)
        self.mat.append(np.asarray(materials, np.uint8))
        self.obj.append(np.full(len(F), obj, np.int32))
        self.nv += len(V)

    def arrays(self):
        if not self.V:
            return (np.zeros((0, 3), np.float32), np.zeros((0, 3), np.int32), np.zeros(0, np.uint8),
                    np.zeros(0, np.int32))
        return (np.concatenate(self.V).astype(np.float32), np.concatenate(self.F).astype(np.int32),
                np.concatenate(self.mat), np.concatenate(self.obj))
