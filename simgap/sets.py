"""Convex sets in R^n with one small set of operations: boxes, zonotopes and ellipsoids.

In the spirit of MPT3's ``Polyhedron``/``Ellipsoid``: each type answers the same queries, so that
the set-based synthesis methods (:mod:`simgap.synthesis.invariant_set`, :mod:`simgap.synthesis.box_tube`),
their controllers and the figures can treat them alike.

* :class:`Box` ``{c + diag(r) z : |z|_inf <= 1}`` (centre c, radius r >= 0);
* :class:`Zonotope` ``{c + G z : |z|_inf <= 1}`` (generators G, n x p);
* :class:`Ellipsoid` ``{x : (x - c)^T P (x - c) <= 1}`` (P positive definite).

Operations (all vectorized over points):

* ``contains(x)``: (B,) bool (a zonotope's membership is an LP: only the box hull's is offered, as
  ``hull_contains``);
* ``bounding_box()``: (lo, hi), exact for every type (a zonotope's is c +- |G| 1, an ellipsoid's
  c +- sqrt(diag P^-1));
* ``plus_box(r)``: the Minkowski sum with the box [-r, r] (exact for boxes and zonotopes, the
  smallest concentric ellipsoid bound {||x - c||_P <= 1 + max_{|v| <= r} ||v||_P} for an ellipsoid);
* ``linear_map(A)``: {A x}: exact (a box becomes a zonotope; an ellipsoid needs A invertible);
* ``support(d)``: h(d) = max over the set of d . x, for directions d (k, n);
* ``project(dims)``: the shadow on some coordinates (the same type);
* ``sample(k, rng)``: k points of the set from a seeded generator (uniform for boxes and ellipsoids,
  c + G z with z uniform in the cube for a zonotope);
* ``outline(dims)``: the closed boundary polygon of the shadow on two coordinates (figures).
"""

from __future__ import annotations

import numpy as np

from .errors import SimgapError


def _dims(dims, n):
    d = [int(i) for i in dims]
    if not d or len(set(d)) != len(d) or not all(0 <= i < n for i in d):
        raise SimgapError(f"projection: need different state indices in 0..{n - 1}, got {list(dims)!r}")
    return d


class Zonotope:
    """{c + G z : |z|_inf <= 1}; G (n, p)."""

    def __init__(self, c, G):
        self.c = np.asarray(c, dtype=float).ravel()
        self.G = np.asarray(G, dtype=float).reshape(self.c.size, -1)

    @property
    def n(self) -> int:
        return self.c.size

    @property
    def radius(self) -> np.ndarray:
        """(n,) half-widths of the bounding box: |G| 1."""
        return np.abs(self.G).sum(axis=1)

    def bounding_box(self):
        r = self.radius
        return self.c - r, self.c + r

    def hull_contains(self, x) -> np.ndarray:
        lo, hi = self.bounding_box()
        x = np.atleast_2d(x)
        return np.all((x >= lo) & (x <= hi), axis=-1)

    def plus_box(self, r) -> "Zonotope":
        return Zonotope(self.c, np.concatenate([self.G, np.diag(np.asarray(r, float) * np.ones(self.n))], axis=1))

    def linear_map(self, A) -> "Zonotope":
        A = np.asarray(A, dtype=float)
        return Zonotope(A @ self.c, A @ self.G)

    def support(self, d) -> np.ndarray:
        d = np.atleast_2d(d)
        return d @ self.c + np.abs(d @ self.G).sum(axis=1)

    def project(self, dims) -> "Zonotope":
        d = _dims(dims, self.n)
        return Zonotope(self.c[d], self.G[d])

    def sample(self, k: int, rng) -> np.ndarray:
        return self.c + rng.uniform(-1.0, 1.0, size=(int(k), self.G.shape[1])) @ self.G.T

    def reduce(self, order: int) -> "Zonotope":
        """An enclosing zonotope with at most ``order`` * n generators (Girard 2005: the generators
        with the smallest ||g||_1 - ||g||_inf are replaced by their box hull)."""
        n, p = self.G.shape
        if p <= order * n:
            return self
        keep = order * n - n
        score = np.abs(self.G).sum(axis=0) - np.abs(self.G).max(axis=0)
        idx = np.argsort(score)
        small, big = self.G[:, idx[:p - keep]], self.G[:, idx[p - keep:]]
        return Zonotope(self.c, np.concatenate([big, np.diag(np.abs(small).sum(axis=1))], axis=1))

    def outline(self, dims=(0, 1)) -> np.ndarray:
        """(k + 1, 2) the shadow's vertices, counter-clockwise, closed (generators sorted by angle)."""
        z = self.project(dims)
        G = z.G[:, np.abs(z.G).sum(axis=0) > 0]
        G = np.where((G[1] < 0) | ((G[1] == 0) & (G[0] < 0)), -G, G)  # all in the upper half plane
        G = G[:, np.argsort(np.arctan2(G[1], G[0]))]
        start = z.c - G.sum(axis=1)
        half = start + np.cumsum(2 * G, axis=1).T
        pts = np.concatenate([start[None], half, (2 * z.c - half)[:-1]], axis=0) if G.shape[1] else z.c[None]
        return np.concatenate([pts, pts[:1]], axis=0)


class Box(Zonotope):
    """{c + diag(r) z : |z|_inf <= 1}: the zonotope with generators diag(r)."""

    def __init__(self, c, r):
        c = np.asarray(c, dtype=float).ravel()
        r = np.broadcast_to(np.asarray(r, dtype=float), c.shape).copy()
        if np.any(r < 0) or not np.all(np.isfinite(r)):
            raise SimgapError(f"box: radii must be finite and >= 0, got {r.tolist()}")
        super().__init__(c, np.diag(r))
        self.r = r

    @classmethod
    def from_bounds(cls, lo, hi) -> "Box":
        lo, hi = np.asarray(lo, float), np.asarray(hi, float)
        return cls(0.5 * (lo + hi), 0.5 * (hi - lo))

    @property
    def radius(self) -> np.ndarray:
        return self.r

    def contains(self, x) -> np.ndarray:
        return self.hull_contains(x)

    def plus_box(self, r) -> "Box":
        return Box(self.c, self.r + np.asarray(r, float))

    def project(self, dims) -> "Box":
        d = _dims(dims, self.n)
        return Box(self.c[d], self.r[d])

    def sample(self, k: int, rng) -> np.ndarray:
        return self.c + rng.uniform(-1.0, 1.0, size=(int(k), self.n)) * self.r

    def vertices(self) -> np.ndarray:
        """(2^n, n) the corners (n <= 16)."""
        if self.n > 16:
            raise SimgapError(f"box: {2 ** self.n} vertices are too many to list (n = {self.n})")
        s = 1.0 - 2.0 * ((np.arange(2 ** self.n)[:, None] >> np.arange(self.n)[None]) & 1)
        return self.c + s * self.r


class Ellipsoid:
    """{x : (x - c)^T P (x - c) <= 1}; P (n, n) positive definite."""

    def __init__(self, c, P):
        self.c = np.asarray(c, dtype=float).ravel()
        P = np.asarray(P, dtype=float).reshape(self.c.size, self.c.size)
        self.P = 0.5 * (P + P.T)
        if np.any(np.linalg.eigvalsh(self.P) <= 0):
            raise SimgapError("ellipsoid: P must be positive definite")

    @property
    def n(self) -> int:
        return self.c.size

    @property
    def radius(self) -> np.ndarray:
        return np.sqrt(np.diag(np.linalg.inv(self.P)))

    def bounding_box(self):
        r = self.radius
        return self.c - r, self.c + r

    def level(self, x) -> np.ndarray:
        e = np.atleast_2d(np.asarray(x, dtype=float)) - self.c
        return np.einsum("bi,ij,bj->b", e, self.P, e)

    def contains(self, x) -> np.ndarray:
        return self.level(x) <= 1.0

    def plus_box(self, r) -> "Ellipsoid":
        b = np.asarray(r, float) * np.ones(self.n)
        if self.n <= 16:  # a convex norm's maximum over the box [-b, b] is at a vertex
            V = Box(np.zeros(self.n), b).vertices()
            k = 1.0 + float(np.sqrt(max(0.0, np.einsum("bi,ij,bj->b", V, self.P, V).max())))
        else:             # the upper bound sqrt(b^T |P| b)
            k = 1.0 + float(np.sqrt(b @ np.abs(self.P) @ b))
        return Ellipsoid(self.c, self.P / k ** 2)

    def linear_map(self, A) -> "Ellipsoid":
        A = np.asarray(A, dtype=float)
        if A.shape != (self.n, self.n) or abs(np.linalg.det(A)) < 1e-300:
            raise SimgapError("ellipsoid: linear_map needs an invertible n x n matrix")
        Q = A @ np.linalg.inv(self.P) @ A.T
        return Ellipsoid(A @ self.c, np.linalg.inv(0.5 * (Q + Q.T)))

    def support(self, d) -> np.ndarray:
        d = np.atleast_2d(d)
        Q = np.linalg.inv(self.P)
        return d @ self.c + np.sqrt(np.einsum("bi,ij,bj->b", d, Q, d))

    def project(self, dims) -> "Ellipsoid":
        """The shadow: the ellipsoid of the matching block of P^-1."""
        d = _dims(dims, self.n)
        Q = np.linalg.inv(self.P)[np.ix_(d, d)]
        return Ellipsoid(self.c[d], np.linalg.inv(0.5 * (Q + Q.T)))

    def sample(self, k: int, rng) -> np.ndarray:
        """Uniform in the ellipsoid: c + L^-T z, z uniform in the unit ball, P = L L^T."""
        z = rng.normal(size=(int(k), self.n))
        z *= (rng.random((int(k), 1)) ** (1.0 / self.n)) / np.linalg.norm(z, axis=1, keepdims=True)
        L = np.linalg.cholesky(self.P)
        return self.c + np.linalg.solve(L.T, z.T).T

    def outline(self, dims=(0, 1), points: int = 181) -> np.ndarray:
        e = self.project(dims)
        L = np.linalg.cholesky(np.linalg.inv(e.P))
        t = np.linspace(0.0, 2 * np.pi, int(points))
        return e.c + np.stack([np.cos(t), np.sin(t)], axis=1) @ L.T
