"""Plain-Python references (the test oracles) for the repertoire's semantics."""

from __future__ import annotations

import numpy as np


def insert(behaviors, qualities, cand_b, cand_q, ok, t_dist, capacity):
    """The paper's sequential insertion rule, one candidate at a time.

    Returns (behaviors, qualities, statuses, archived (behavior, quality) pairs in order).
    """
    b = [np.asarray(x, np.float32) for x in behaviors]
    q = [np.float32(x) for x in qualities]
    status, archived = [], []
    t2 = np.float32(t_dist) ** 2
    for i, (c, cq) in enumerate(zip(np.asarray(cand_b, np.float32), np.asarray(cand_q, np.float32), strict=True)):
        if not ok[i]:
            status.append("skipped")
            continue
        if b:
            d2 = np.array([np.sum((x - c) ** 2, dtype=np.float32) for x in b], np.float32)
            j = int(np.argmin(d2))
        if not b or d2[j] > t2:
            if len(b) < capacity:
                b.append(c)
                q.append(cq)
                status.append("added")
            else:
                status.append("dropped")
                archived.append((c, cq))
        elif cq > q[j]:
            archived.append((b[j], q[j]))
            b[j], q[j] = c, cq
            status.append("replaced")
        else:
            status.append("rejected")
            archived.append((c, cq))
    return np.array(b).reshape(-1, 2), np.array(q, np.float32), status, archived


def novelty(behaviors, k):
    """Mean distance to the k nearest other behaviors (fewer if fewer exist)."""
    b = np.asarray(behaviors, np.float64)
    if len(b) < 2:
        return np.zeros(len(b))
    d = np.sqrt(((b[:, None] - b[None]) ** 2).sum(-1))
    np.fill_diagonal(d, np.inf)
    d.sort(axis=1)
    m = min(k, len(b) - 1)
    return d[:, :m].mean(1)
