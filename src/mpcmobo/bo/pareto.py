"""Pareto dominance, hypervolume and the reference-point rule (minimisation).

All functions here work on *costs to be minimised*, ``Y`` of shape (n, m), in the units the
caller observed them in (no sign flip). Rows containing NaN or inf are never Pareto-optimal
and contribute no hypervolume.

Dominance (paper, Definition of Pareto optimality, section 3): ``a`` dominates ``b`` iff
``a_i <= b_i`` for every objective and ``a_j < b_j`` for at least one.

Hypervolume (paper, section 3): the Lebesgue measure of the region dominated by the set and
dominating the reference point ``r``, ``V(P) = vol{z : exists p in P, p <= z <= r}``.
"""

from __future__ import annotations

import moocore
import numpy as np

__all__ = ["finite_rows", "hypervolume", "pareto_mask", "reference_point"]


def finite_rows(Y: np.ndarray) -> np.ndarray:
    """Boolean (n,) mask of rows of ``Y`` (n, m) whose entries are all finite."""
    Y = np.asarray(Y, dtype=np.float64)
    if Y.ndim == 1:
        Y = Y[:, None]
    return np.all(np.isfinite(Y), axis=1)


def pareto_mask(Y: np.ndarray) -> np.ndarray:
    """Non-dominated rows of ``Y`` (n, m) for minimisation.

    Returns a bool (n,) array, True where no other row dominates the row. Exact duplicates do
    not dominate each other, so all copies of a Pareto point are kept. Non-finite rows are
    False and are ignored as dominators. The test itself is ``moocore.is_nondominated``
    (``keep_weakly=True``: duplicates kept) on the finite rows.
    """
    Y = np.asarray(Y, dtype=np.float64)
    if Y.ndim == 1:
        Y = Y[:, None]
    ok = finite_rows(Y)
    mask = np.zeros(Y.shape[0], dtype=bool)
    if ok.any():
        mask[ok] = moocore.is_nondominated(Y[ok], keep_weakly=True)
    return mask


def hypervolume(Y: np.ndarray, ref: np.ndarray) -> float:
    """Hypervolume of the finite rows of ``Y`` (n, m) w.r.t. ``ref`` (m,), minimisation.

    Computed with ``moocore.hypervolume``. Points that do not strictly dominate ``ref`` in
    every objective add nothing; an empty set has hypervolume 0.
    """
    Y = np.asarray(Y, dtype=np.float64)
    if Y.ndim == 1:
        Y = Y[None, :]
    ref = np.asarray(ref, dtype=np.float64).reshape(-1)
    Y = Y[finite_rows(Y)]
    Y = Y[np.all(Y < ref, axis=1)]
    if Y.shape[0] == 0:
        return 0.0
    return float(moocore.hypervolume(Y, ref=ref))


def reference_point(Y: np.ndarray, margin: float = 0.1) -> np.ndarray:
    """The fixed reference-point rule, in minimisation units.

    ``r_i = max_k Y_ki + margin * (max_k Y_ki - min_k Y_ki)`` over the finite rows, i.e. the
    nadir of the observations plus ``margin`` times their range, per objective. If an
    objective has zero range the margin is taken relative to ``max(|max_k Y_ki|, 1)``.

    The learner calls this ONCE, on the initial design, and keeps ``r`` fixed for the whole
    run: it is not a moving point recomputed from the growing data set (a moving ``r`` makes
    hypervolumes of different iterations incomparable and changes the acquisition's target).
    """
    Y = np.asarray(Y, dtype=np.float64)
    if Y.ndim == 1:
        Y = Y[:, None]
    Y = Y[finite_rows(Y)]
    if Y.shape[0] == 0:
        raise ValueError("reference_point needs at least one finite observation")
    hi = Y.max(axis=0)
    rng = hi - Y.min(axis=0)
    rng = np.where(rng > 0, rng, np.maximum(np.abs(hi), 1.0))
    return hi + margin * rng
