"""A bounded cache of rendered reference descriptors, for query streams (a robot, an app).

Render mode renders each retrieved reference image's keypoint patches *from that reference
camera*, so its descriptors depend on the map and the config only, never on the query: a
stream of nearby queries retrieves the same references again and again. The cache keeps the
most recently used references' descriptors (float16, as hloc stores descriptors) within a
budget in megabytes and evicts the least recently used; a budget of 0 disables it. It trades
memory for render time at query time only: the map on disk is unchanged.
"""

from __future__ import annotations

from collections import OrderedDict

import numpy as np


class DescriptorCache:
    """Least-recently-used map ``reference index -> descriptors [K_max, D]`` within a budget.

    Args:
      budget_mb: bytes allowed for the stored descriptors, in MB (1e6 bytes).
    """

    def __init__(self, budget_mb: float):
        self.budget = int(max(0.0, budget_mb) * 1e6)
        self._items: OrderedDict[int, np.ndarray] = OrderedDict()
        self.bytes = 0
        self.hits = 0
        self.misses = 0
        self.evictions = 0

    def get(self, i: int) -> np.ndarray | None:
        """The descriptors of reference ``i`` (float32) or None (counted as a miss: the caller
        renders it); a hit becomes most recent."""
        d = self._items.get(int(i))
        if d is None:
            self.misses += 1
            return None
        self.hits += 1
        self._items.move_to_end(int(i))
        return d.astype(np.float32)

    def put(self, i: int, desc: np.ndarray) -> None:
        """Store reference ``i``'s descriptors [K_max, D], evicting the least recently used."""
        d = np.asarray(desc, np.float16)
        if d.nbytes > self.budget:
            return
        i = int(i)
        if i in self._items:
            self.bytes -= self._items.pop(i).nbytes
        while self.bytes + d.nbytes > self.budget and self._items:
            _, old = self._items.popitem(last=False)
            self.bytes -= old.nbytes
            self.evictions += 1
        self._items[i] = d
        self.bytes += d.nbytes

    def __contains__(self, i: int) -> bool:
        return int(i) in self._items

    def __len__(self) -> int:
        return len(self._items)

    def stats(self) -> dict[str, float]:
        return {"entries": len(self), "bytes": self.bytes, "budget_bytes": self.budget,
                "hits": self.hits, "misses": self.misses, "evictions": self.evictions}
