"""A hash table from 2-D points to integers, looked up and filled a whole array at a time.

The illumination mesher (`_illumination_evaluator`) caches tens of millions of exact values by
the coordinates of their point. A Python `dict` keyed by `complex(x, y)` costs a Python object
per key and per value and a bytecode round trip per look-up: on the box scene at tol 1e-4 the
dict's look-ups took more time than the engine's evaluations, and its entries most of the
memory. `KeyTable` keeps the keys (`complex128`, the point's exact coordinates) and values
(`int64`) in two NumPy arrays, open addressing with linear probing (Knuth, TAOCP vol. 3,
§6.4, Algorithm L), each probe step done for every pending key at once.

Keys compare as `complex128` values (`x + iy`), as the `dict` did: `-0.0` and `0.0` are the same
key (keys are normalised by adding `0.0`, so both hash alike); NaN keys are not supported.
"""

from __future__ import annotations

import numpy as np

EMPTY, GONE = -1, -2  # slot markers in `vals`: never used / deleted (a tombstone: probing goes on;
# its slot is not used again until the table is rebuilt)
SMALL = 512  # below this many keys, `first_occurrence` sorts
MAX_LOAD = 0.6  # occupied (live and deleted) slots per slot before the table doubles
_C1, _C2, _C3 = np.uint64(0x9E3779B97F4A7C15), np.uint64(0xC2B2AE3D27D4EB4F), np.uint64(0x94D049BB133111EB)


def as_keys(xy: np.ndarray) -> np.ndarray:
    """Points `(n, 2)` (float64) as keys `(n,)` (complex128 `x + iy`, `-0.0` made `0.0`)."""
    xy = np.ascontiguousarray(np.asarray(xy, np.float64).reshape(-1, 2))
    return xy.view(np.complex128).ravel() + 0.0


class KeyTable:
    """Map from `complex128` keys to non-negative `int64` values (a set: values 0).

    Example:
        >>> t = KeyTable()
        >>> t.put(np.array([1 + 2j, 3j]), np.array([7, 8]))
        >>> t.get(np.array([3j, 5 + 0j])).tolist()
        [8, -1]
    """

    def __init__(self, capacity: int = 1024):
        cap = 1 << max(4, int(capacity - 1).bit_length())
        self.keys = np.zeros(cap, np.complex128)
        self.vals = np.full(cap, EMPTY, np.int64)
        self.live = 0
        self.used = 0  # live and deleted slots

    def __len__(self) -> int:
        return self.live

    def copy(self) -> KeyTable:
        out = KeyTable.__new__(KeyTable)
        out.keys, out.vals, out.live, out.used = self.keys.copy(), self.vals.copy(), self.live, self.used
        return out

    def _hash(self, k: np.ndarray) -> np.ndarray:
        u = k.view(np.uint64).reshape(-1, 2)
        h = (u[:, 0] * _C1) ^ (u[:, 1] * _C2)
        h ^= h >> np.uint64(31)
        h *= _C3
        h ^= h >> np.uint64(29)
        return (h & np.uint64(self.keys.size - 1)).astype(np.int64)

    def _slots(self, k: np.ndarray) -> np.ndarray:
        """The slot `(n,)` holding each key, -1 when absent."""
        k = k + 0.0
        out = np.full(k.size, -1, np.int64)
        idx = np.arange(k.size)
        h = self._hash(k)
        mask = self.keys.size - 1
        while idx.size:
            v = self.vals[h]
            hit = (v >= 0) & (self.keys[h] == k[idx])
            out[idx[hit]] = h[hit]
            go = (v != EMPTY) & ~hit
            idx, h = idx[go], (h[go] + 1) & mask
        return out

    def get(self, k: np.ndarray, default: int = -1) -> np.ndarray:
        """The values `(n,)` of keys `k (n,)`, `default` for absent keys."""
        k = np.asarray(k, np.complex128).ravel()
        s = self._slots(k)
        return np.where(s >= 0, self.vals[np.maximum(s, 0)], default)

    def contains(self, k: np.ndarray) -> np.ndarray:
        """`(n,)` bool: whether each key is in the table."""
        return self._slots(np.asarray(k, np.complex128).ravel()) >= 0

    def _claim(self, k: np.ndarray, v: np.ndarray) -> np.ndarray:
        """The slot `(n,)` of each key, inserting absent keys with their value in `v` (the first
        occurrence's, for a key repeated in `k`). No sorting: where several keys probe the same
        free slot, each writes a claim into it and the one that reads its own back (the first
        key: claims are written in reverse) takes it; the others look at it again."""
        n = k.size
        if self.used + n > MAX_LOAD * self.keys.size:
            self._resize(self.live + n)
        out = np.empty(n, np.int64)
        idx = np.arange(n)
        h = self._hash(k)
        mask = self.keys.size - 1
        vals, keys = self.vals, self.keys
        while idx.size:
            cur = vals[h]
            hit = (cur >= 0) & (keys[h] == k[idx])
            out[idx[hit]] = h[hit]
            free = cur == EMPTY  # (a deleted slot is passed: the key may lie further on)
            if np.any(free):
                fh, fi = h[free], idx[free]
                was = cur[free]
                vals[fh[::-1]] = -3 - fi[::-1]  # claims (below EMPTY and GONE)
                win = vals[fh] == -3 - fi
                vals[fh] = was  # undo; the winners write below
                ws, wi = fh[win], fi[win]
                self.used += int(ws.size)
                keys[ws], vals[ws] = k[wi], v[wi]
                out[wi] = ws
                self.live += ws.size
                taken = np.zeros(idx.size, bool)
                taken[np.nonzero(free)[0][win]] = True
                hit |= taken
            step = ~hit & ~free  # occupied by another key: probe on; losing claimants look again
            h = np.where(step, (h + 1) & mask, h)
            keep = ~hit
            idx, h = idx[keep], h[keep]
        return out

    def put(self, k: np.ndarray, v: np.ndarray | int = 0) -> None:
        """Set keys `k (n,)` to values `v` (`(n,)` or one value, >= 0); with repeated keys the
        last value wins."""
        k = np.asarray(k, np.complex128).ravel() + 0.0
        v = np.ascontiguousarray(np.broadcast_to(np.asarray(v, np.int64), k.shape))
        if k.size == 0:
            return
        s = self._claim(k, v)
        self.vals[s] = v  # (a repeated slot takes the last of its values)

    def delete(self, k: np.ndarray) -> np.ndarray:
        """Remove keys `k (n,)`; returns their values (-1 for absent keys)."""
        k = np.asarray(k, np.complex128).ravel()
        s = self._slots(k)
        out = np.where(s >= 0, self.vals[np.maximum(s, 0)], -1)
        gone = np.unique(s[s >= 0])
        self.vals[gone] = GONE
        self.live -= gone.size
        return out

    def items(self) -> tuple[np.ndarray, np.ndarray]:
        """The live keys and their values (in slot order)."""
        ok = self.vals >= 0
        return self.keys[ok], self.vals[ok]

    def _resize(self, live: int) -> None:
        k, v = self.items()
        cap = 1 << max(4, int(np.ceil(1.5 * live / MAX_LOAD)).bit_length())  # load below 0.4
        self.keys = np.zeros(cap, np.complex128)
        self.vals = np.full(cap, EMPTY, np.int64)
        self.live = self.used = 0
        if k.size:
            self.put(k, v)


def first_occurrence(k: np.ndarray) -> np.ndarray:
    """`(n,)` bool: whether each key of `k (n,)` is its first occurrence in `k` (a hash table's
    pass, no sort).

    Example:
        >>> first_occurrence(np.array([1j, 2j, 1j, 3j])).tolist()
        [True, True, False, True]
    """
    k = np.asarray(k, np.complex128).ravel() + 0.0
    if k.size < SMALL:  # (a sort costs less than the table's set-up)
        out = np.zeros(k.size, bool)
        out[np.unique(k, return_index=True)[1]] = True
        return out
    t = KeyTable(int(k.size / MAX_LOAD) + 1)
    idx = np.arange(k.size)
    return t.vals[t._claim(k, idx)] == idx  # type: ignore[no-any-return]
