"""Descriptor matching within coarse vocabulary nodes (ORB-SLAM's ``SearchByBoW``).

Mutual nearest neighbours over every pair of two descriptor sets cost P x N Hamming distances; verifying a
place candidate is mostly that. DBoW2's vocabulary is a tree, and ORB-SLAM compares only descriptors under the
same node a few levels above the words. Ours is one flat level of words (``vocabulary.py``), so the level above
is made here: the words grouped into ``K`` coarse nodes by the same k-majority that trained them (seed 0, so the
same nodes every run). Two views of one point are often tens of bits apart and then fall into different
nodes, so each query descriptor is looked for in its ``probes`` nearest nodes, the other side in its nearest
one: at K=16 and three probes a match is sought among ~1/5 of the pairs. Within a node the ratio test sees
fewer distractors, which gives back part of what the nodes miss: on TUM teddy keyframe-to-frame matchings
0.33-0.67 s apart the PnP after it kept a median 97-100 % of the inliers that matching every pair gave
(docs/loop.md, "Matching within coarse nodes").
"""

from __future__ import annotations

import numpy as np

from vslam.loop.vocabulary import Vocabulary, train_vocabulary, unpack_pm1


class CoarseNodes:
    """``K`` coarse nodes over a vocabulary's words; ``nodes(desc, probes)`` assigns binary descriptors."""

    def __init__(self, vocab: Vocabulary, k: int = 16, seed: int = 0):
        k = min(k, vocab.size)
        self.k = k
        nodes = train_vocabulary([vocab.words], k, np.random.default_rng(seed), iterations=30)
        self._pm1 = unpack_pm1(nodes.words)  # (K,256) +-1 centres

    def nodes(self, desc: np.ndarray, probes: int = 1) -> np.ndarray:
        """(N,32) uint8 -> (N,t) int64, t = min(probes, K): the t nearest nodes of each descriptor (Hamming to
        the node centres), nearest first, ties to the lower node."""
        probes = min(probes, self.k)
        if len(desc) == 0:
            return np.zeros((0, probes), np.int64)
        dots = unpack_pm1(desc) @ self._pm1.T  # the largest dot is the smallest Hamming distance
        out = np.empty((len(desc), probes), np.int64)
        rows = np.arange(len(desc))
        for p in range(probes):
            out[:, p] = np.argmax(dots, axis=1)
            dots[rows, out[:, p]] = -np.inf
        return out


def match_in_nodes(d1: np.ndarray, n1: np.ndarray, d2: np.ndarray, p2: np.ndarray, ratio: float | None = 0.8,
                   max_dist: float = np.inf) -> np.ndarray:
    """``match_mutual`` (vslam.features.matching) among the pairs that share a node: row i of d1 (P,D) uint8,
    in node n1[i] (P,), is compared with the rows j of d2 (N,D) whose probes p2[j] (N,t) hold that node.

    Each row's nearest and second nearest column, and each column's nearest row, among those pairs; a pair is
    kept when mutual, <= ``max_dist`` bits and (``ratio`` not None) < ratio x the row's second-best distance
    (none: passes). Ties go to the lower index, as in ``match_mutual``. -> (M,2) (i, j) pairs, i ascending."""
    n_rows, n_cols = len(d1), len(d2)
    if n_rows == 0 or n_cols == 0:
        return np.zeros((0, 2), np.int64)
    a = np.ascontiguousarray(d1).view(np.uint64)  # (P,W) 64-bit words
    b = np.ascontiguousarray(d2).view(np.uint64)
    # keys distance * (count + 1) + index: the smaller key is the nearer, then the lower index; int32 holds them
    # (<= 256 bits x a few thousand descriptors) and partitions faster than int64
    big = np.iinfo(np.int32).max
    best = np.full(n_rows, big, np.int32)  # per row: the key of its nearest column
    second = np.full(n_rows, big, np.int32)  # ... and of its second nearest
    col_best = np.full(n_cols, big, np.int32)  # per column: the key of its nearest row
    # a column's probes are distinct nodes (``CoarseNodes.nodes``), so it meets each row at most once
    probe_cols = np.repeat(np.arange(n_cols, dtype=np.int32), p2.shape[1])
    probe_nodes = p2.ravel()
    k = int(max(n1.max(), probe_nodes.max())) + 1
    row_order = np.argsort(n1, kind="stable").astype(np.int32)
    row_start = np.searchsorted(n1[row_order], np.arange(k + 1))
    col_order = np.argsort(probe_nodes, kind="stable")
    col_start = np.searchsorted(probe_nodes[col_order], np.arange(k + 1))
    for c in range(k):
        rows = row_order[row_start[c]:row_start[c + 1]]
        cols = probe_cols[col_order[col_start[c]:col_start[c + 1]]]
        if len(rows) == 0 or len(cols) == 0:
            continue
        ar, bt = np.take(a, rows, axis=0), np.ascontiguousarray(np.take(b, cols, axis=0).T)
        x = np.empty((len(rows), len(cols)), np.uint64)
        bits = np.empty((len(rows), len(cols)), np.uint8)
        D = np.zeros((len(rows), len(cols)), np.uint16)
        for w in range(a.shape[1]):  # a word at a time: (rows, cols) popcounts summed in place
            np.bitwise_xor(ar[:, w, None], bt[w], out=x)
            np.bitwise_count(x, out=bits)
            D += bits
        key = D.astype(np.int32)
        key *= np.int32(n_cols + 1)
        key += cols
        r = np.arange(len(rows))
        j = key.argmin(axis=1)
        best[rows] = key[r, j]
        key[r, j] = big
        second[rows] = key.min(axis=1)  # big: the row had one candidate
        key = D.astype(np.int32)
        key *= np.int32(n_rows + 1)
        key += rows[:, None]
        col_best[cols] = np.minimum(col_best[cols], key.min(axis=0))
    has = np.flatnonzero(best != big)
    best_d, best_j = np.divmod(best[has].astype(np.int64), n_cols + 1)
    ok = (col_best[best_j] % (n_rows + 1) == has) & (best_d <= max_dist)
    if ratio is not None:
        sec = second[has].astype(np.int64)
        ok &= np.where(sec != big, best_d < ratio * (sec // (n_cols + 1)), True)
    return np.stack([has[ok], best_j[ok]], axis=1).astype(np.int64).reshape(-1, 2)
