"""Analytic plate surfaces with known answers, triangulated on a grid (plate frame, mm).

``z = f(x, y)`` over the 1200 x 800 mm plate centred on the origin: the sail (a dish,
``z = x^2 / 2Rx + y^2 / 2Ry`` with Rx = 3000 mm, Ry = 2000 mm) and a lopsided sail (plus a cubic term,
so it is not symmetric under a half turn and the corner order matters). Used by the registration,
template and metric tests, where every expected answer follows from the formula.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from analysis.design.mesh import TriMesh

__all__ = ["L_MM", "W_MM", "corners", "grid_mesh", "lopsided", "sail", "ship_pose"]

L_MM, W_MM = 1200.0, 800.0

Surface = Callable[[np.ndarray, np.ndarray], np.ndarray]


def sail(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """The sail's height (mm) at plate-frame (x, y) mm."""
    return x**2 / 6000.0 + y**2 / 4000.0


def lopsided(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """A sail with a cubic term: not symmetric under a half turn, so the corner order matters."""
    return sail(x, y) + x**3 / 2.0e7


def grid_mesh(f: Surface, step_mm: float = 10.0) -> TriMesh:
    """The surface ``f`` over the whole plate as a grid mesh with ``step_mm`` spacing."""
    xs = np.linspace(-L_MM / 2, L_MM / 2, round(L_MM / step_mm) + 1)
    ys = np.linspace(-W_MM / 2, W_MM / 2, round(W_MM / step_mm) + 1)
    X, Y = np.meshgrid(xs, ys)
    V = np.column_stack([X.ravel(), Y.ravel(), f(X, Y).ravel()])
    nx = len(xs)
    i, j = np.meshgrid(np.arange(nx - 1), np.arange(len(ys) - 1))
    k = (j * nx + i).ravel()
    T = np.vstack([np.column_stack([k, k + 1, k + nx + 1]), np.column_stack([k, k + nx + 1, k + nx])])
    return TriMesh(V, T)


def corners(f: Surface = sail) -> np.ndarray:
    """(4, 3) the plate's corners on ``f``, counter-clockwise from (-L/2, -W/2)."""
    c = np.array([[-L_MM / 2, -W_MM / 2], [L_MM / 2, -W_MM / 2], [L_MM / 2, W_MM / 2], [-L_MM / 2, W_MM / 2]])
    return np.column_stack([c, f(c[:, 0], c[:, 1])])


def ship_pose() -> np.ndarray:
    """T_ship_design (4, 4) mm: a side-shell pose, stood up 75 degrees, turned 20, 13 m above the keel."""
    a, b = np.radians(75.0), np.radians(20.0)
    Rx = np.array([[1, 0, 0], [0, np.cos(a), -np.sin(a)], [0, np.sin(a), np.cos(a)]])
    Rz = np.array([[np.cos(b), -np.sin(b), 0], [np.sin(b), np.cos(b), 0], [0, 0, 1]])
    T = np.eye(4)
    T[:3, :3] = Rz @ Rx
    T[:3, 3] = [61000.0, 9000.0, 13000.0]
    return T
