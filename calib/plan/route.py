"""Open tours over candidate configurations (issue 27): the seconds of a visiting order, the
cheapest place to insert one more, and 2-opt — for the sequential design's batch plan
(``calib.plan.adaptive.SequentialDesign.plan_route``).

Nodes are indices into a cost matrix ``cost`` (k, k) of move seconds between configurations,
node 0 being where the robot stands; a path is a list of nodes starting with 0 (an open tour:
the robot does not return). Pure numpy.
"""

from __future__ import annotations

import numpy as np


def path_seconds(path, cost: np.ndarray) -> float:
    """Move seconds along ``path`` (nodes, first = where the robot stands)."""
    p = np.asarray(path, dtype=int)
    return float(cost[p[:-1], p[1:]].sum()) if len(p) > 1 else 0.0


def insertion_costs(path, cost: np.ndarray, nodes: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """For each of ``nodes`` (m,), the extra move seconds of its cheapest insertion into ``path``
    (after the robot's node, between two stops, or at the end) and the position it goes to
    (index into the path after which it is inserted). Returns ((m,) s, (m,) int)."""
    p = np.asarray(path, dtype=int)
    n = np.asarray(nodes, dtype=int)
    if len(p) == 1:
        return cost[p[0], n].astype(float), np.zeros(len(n), dtype=int)
    a, b = p[:-1], p[1:]
    between = cost[a][:, n] + cost[n][:, b].T - cost[a, b][:, None]  # (k-1, m)
    at_end = cost[p[-1], n][None, :]
    allc = np.vstack([between, at_end])  # (k, m): row i = after path[i]
    pos = np.argmin(allc, axis=0)
    return allc[pos, np.arange(len(n))], pos


def two_opt(path, cost: np.ndarray, max_passes: int = 20) -> list[int]:
    """Shorten an open path whose first node is fixed by reversing segments while that helps
    (the cost matrix may be asymmetric in principle; motion times are symmetric)."""
    p = [int(x) for x in path]
    k = len(p)
    if k < 3:
        return p
    cost = np.asarray(cost, dtype=float).tolist()  # plain lists: this loop is scalar work
    for _ in range(max_passes):
        improved = False
        for i in range(1, k - 1):
            for j in range(i + 1, k):
                before = cost[p[i - 1]][p[i]] + (cost[p[j]][p[j + 1]] if j + 1 < k else 0.0)
                after = cost[p[i - 1]][p[j]] + (cost[p[i]][p[j + 1]] if j + 1 < k else 0.0)
                if after < before - 1e-9:
                    p[i:j + 1] = p[i:j + 1][::-1]
                    improved = True
        if not improved:
            break
    return p


def nearest_neighbour(cost: np.ndarray, nodes) -> list[int]:
    """Open path from node 0 through ``nodes``, always to the cheapest one not yet visited."""
    left = [int(x) for x in nodes]
    path = [0]
    while left:
        k = int(np.argmin(cost[path[-1], left]))
        path.append(left.pop(k))
    return path
