"""Descriptor matching for unit-norm float descriptors (numpy only)."""
from __future__ import annotations

import numpy as np


def match_mutual_nn(
    desc_a: np.ndarray, desc_b: np.ndarray, max_distance: float = 0.9, ratio: float | None = 0.9
) -> np.ndarray:
    """Mutual nearest neighbours between two sets of L2-normalised descriptors.

    Args:
        desc_a, desc_b: [Na, D] and [Nb, D] float arrays with unit rows.
        max_distance: reject pairs whose L2 distance is larger (unit vectors: 0..2).
        ratio: Lowe's ratio test on distances (best / second best, in a's view); None disables it.

    Returns:
        [M, 2] int64 index pairs (i into a, j into b), ordered by i.
    """
    if len(desc_a) == 0 or len(desc_b) == 0:
        return np.empty((0, 2), dtype=np.int64)
    if desc_a.shape[1] != desc_b.shape[1]:
        raise ValueError(f"descriptor sizes differ: {desc_a.shape[1]} vs {desc_b.shape[1]}")
    sim = np.asarray(desc_a, dtype=np.float32) @ np.asarray(desc_b, dtype=np.float32).T
    best_b = np.argmax(sim, axis=1)
    best_sim = sim[np.arange(len(desc_a)), best_b]
    # Mutual: a's best in b is also best for that column (max over axis 0 is fast, argmax over it is not).
    rows = np.flatnonzero(best_sim >= sim.max(axis=0)[best_b])
    cols = best_b[rows]
    # A column that ties for several rows has no mutual best: drop it (binary descriptors tie often).
    _, inverse, counts = np.unique(cols, return_inverse=True, return_counts=True)
    rows, cols = rows[counts[inverse] == 1], cols[counts[inverse] == 1]
    best_sim = best_sim[rows]
    dist = np.sqrt(np.maximum(2.0 - 2.0 * best_sim, 0.0))
    keep = dist <= max_distance
    if ratio is not None and sim.shape[1] > 1:
        # Second best only for the surviving rows (a full partition of sim costs more than the matmul).
        candidates = sim[rows[keep]]
        candidates[np.arange(len(candidates)), cols[keep]] = -np.inf
        second = np.sqrt(np.maximum(2.0 - 2.0 * candidates.max(axis=1), 0.0))
        keep[keep] = dist[keep] <= ratio * second
    return np.stack([rows[keep], cols[keep]], axis=1).astype(np.int64)
