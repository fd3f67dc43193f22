"""Keyframe database for place recognition: one row per keyframe, search by matrix product.

Descriptors are unit vectors, so the similarity is a dot product and a query
against every keyframe is one (K,D) x (D,) product, fast enough in numpy
without an index even for tens of thousands of keyframes (docs/loop.md,
"Keyframe database"). Rows are
stored in a growing float32 matrix (amortised doubling) so adding is O(1).
"""

from __future__ import annotations

import numpy as np


class KeyframeDatabase:
    """kf id -> (D,) float32 unit descriptor; ``query`` returns the top-k most similar keyframes."""

    def __init__(self, dim: int):
        self.dim = dim
        self._mat = np.zeros((16, dim), np.float32)
        self._ids: list[int] = []
        self._row: dict[int, int] = {}

    def __len__(self) -> int:
        return len(self._ids)

    def __contains__(self, kf_id: int) -> bool:
        return kf_id in self._row

    def add(self, kf_id: int, vec: np.ndarray) -> None:
        if kf_id in self._row:
            self._mat[self._row[kf_id]] = vec
            return
        if len(self._ids) == len(self._mat):
            self._mat = np.concatenate([self._mat, np.zeros_like(self._mat)])
        self._row[kf_id] = len(self._ids)
        self._mat[len(self._ids)] = vec
        self._ids.append(int(kf_id))

    def remove(self, kf_id: int) -> None:
        """Drop a keyframe (the last row moves into its slot)."""
        r = self._row.pop(kf_id, None)
        if r is None:
            return
        last = len(self._ids) - 1
        if r != last:
            self._mat[r] = self._mat[last]
            self._ids[r] = self._ids[last]
            self._row[self._ids[r]] = r
        self._ids.pop()

    def vector(self, kf_id: int) -> np.ndarray:
        return self._mat[self._row[kf_id]]

    def ids(self) -> np.ndarray:
        return np.array(self._ids, np.int64)

    def matrix(self) -> np.ndarray:
        """(K,D) rows in ``ids()`` order (a view)."""
        return self._mat[: len(self._ids)]

    def scores(self, vec: np.ndarray) -> np.ndarray:
        """(K,) similarity of ``vec`` to every stored keyframe, in ``ids()`` order."""
        return self.matrix() @ np.asarray(vec, np.float32)

    def query(self, vec: np.ndarray, k: int, exclude: set[int] | frozenset[int] = frozenset(),
              min_score: float = -np.inf) -> list[tuple[int, float]]:
        """[(kf id, score)] of the ``k`` best keyframes not in ``exclude`` with score >= min_score,
        best first (ties: lower id first)."""
        if not self._ids:
            return []
        s = self.scores(vec)
        ids = self.ids()
        order = np.lexsort((ids, -s))
        out: list[tuple[int, float]] = []
        for i in order:
            if s[i] < min_score or len(out) >= k:
                break
            if int(ids[i]) not in exclude:
                out.append((int(ids[i]), float(s[i])))
        return out

    def memory_bytes(self) -> int:
        """Bytes used by the stored rows (the allocated matrix may be up to 2x this)."""
        return len(self._ids) * self.dim * 4
