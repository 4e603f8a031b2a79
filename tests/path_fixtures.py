"""Small reference paths for environment tests (iiwa joint space)."""

import numpy as np

from mjx_pathtrack.robots import iiwa
from mjx_pathtrack.core import spline as S


def random_walk_paths(n_paths=6, n_knots=30, seed=0, max_knots=32):
    rng = np.random.default_rng(seed)
    paths = []
    for _ in range(n_paths):
        k = np.cumsum(rng.normal(0.0, 0.12, (n_knots, 7)), 0) + rng.uniform(-1, 1, 7)
        paths.append(S.make_path(np.clip(k, -0.9 * iiwa.POS, 0.9 * iiwa.POS), max_knots=max_knots))
    return S.stack_paths(paths)


def line_path(length=1.0, joint=0, n_knots=6):
    knots = np.zeros((n_knots, 7))
    knots[:, joint] = np.linspace(0.0, length, n_knots)
    return S.stack_paths([S.make_path(knots)])
