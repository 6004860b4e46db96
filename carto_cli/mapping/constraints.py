"""Node–submap constraints as Cartographer's PoseGraph keeps them, stored struct-of-arrays.

A constraint says where a node (a scan) sits in a submap's frame: ``relative_pose``
is the node's pose expressed in the submap frame, i.e. ``inverse(submap) ∘ node``.
Intra-submap constraints come from local SLAM inserting the scan into the submap;
inter-submap ones (loop closures) from the constraint builder's scan matching.

The optimizer reads whole columns at once, and the constraint builder adds a few
constraints at a time, so :class:`ConstraintSet` keeps growable arrays (doubling
capacity, amortised O(1) ``add``) and hands out views of the filled prefix.
"""
from __future__ import annotations

import enum
from collections.abc import Iterable, Iterator
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike


class ConstraintKind(enum.IntEnum):
    INTRA_SUBMAP = 0
    INTER_SUBMAP = 1  # a loop closure; robustified by the Huber loss


@dataclass(frozen=True)
class Constraint:
    """One constraint, for building and inspecting; the solver never sees these."""

    submap: int
    node: int
    relative_pose: np.ndarray  # (x, y, theta) of the node in the submap frame
    translation_weight: float
    rotation_weight: float
    kind: ConstraintKind = ConstraintKind.INTRA_SUBMAP

    @property
    def is_loop_closure(self) -> bool:
        return self.kind == ConstraintKind.INTER_SUBMAP


class ConstraintSet:
    """Growable struct-of-arrays of constraints.

    The column properties (``submap``, ``node``, ``relative``, ...) are views of
    the filled part. They alias the storage until the next ``add``/``extend``
    reallocates it, so treat them as read-only snapshots.
    """

    _COLUMNS = ("_submap", "_node", "_relative", "_translation_weight", "_rotation_weight", "_loop")

    def __init__(self, capacity: int = 64):
        capacity = max(int(capacity), 1)
        self._n = 0
        self._submap = np.empty(capacity, dtype=np.int64)
        self._node = np.empty(capacity, dtype=np.int64)
        self._relative = np.empty((capacity, 3), dtype=np.float64)
        self._translation_weight = np.empty(capacity, dtype=np.float64)
        self._rotation_weight = np.empty(capacity, dtype=np.float64)
        self._loop = np.empty(capacity, dtype=bool)

    # ------------------------------------------------------------------ construction

    @classmethod
    def from_arrays(cls, submap: ArrayLike, node: ArrayLike, relative: ArrayLike, translation_weight: ArrayLike,
                    rotation_weight: ArrayLike, is_loop_closure: ArrayLike = False) -> ConstraintSet:
        submap = np.atleast_1d(np.asarray(submap, dtype=np.int64))
        out = cls(capacity=len(submap))
        out.extend(submap, node, relative, translation_weight, rotation_weight, is_loop_closure)
        return out

    @classmethod
    def from_constraints(cls, constraints: Iterable[Constraint]) -> ConstraintSet:
        out = cls()
        for c in constraints:
            out.add(c.submap, c.node, c.relative_pose, c.translation_weight, c.rotation_weight,
                    c.is_loop_closure)
        return out

    def _reserve(self, needed: int) -> None:
        capacity = len(self._submap)
        if needed <= capacity:
            return
        while capacity < needed:
            capacity *= 2
        for name in self._COLUMNS:
            old = getattr(self, name)
            new = np.empty((capacity,) + old.shape[1:], dtype=old.dtype)
            new[: self._n] = old[: self._n]
            setattr(self, name, new)

    def add(self, submap: int, node: int, relative_pose: ArrayLike, translation_weight: float,
            rotation_weight: float, is_loop_closure: bool | ConstraintKind = False) -> int:
        """Append one constraint and return its index."""
        self._reserve(self._n + 1)
        i = self._n
        self._submap[i] = submap
        self._node[i] = node
        self._relative[i] = relative_pose
        self._translation_weight[i] = translation_weight
        self._rotation_weight[i] = rotation_weight
        self._loop[i] = bool(is_loop_closure)
        self._n += 1
        return i

    def extend(self, submap: ArrayLike, node: ArrayLike, relative: ArrayLike, translation_weight: ArrayLike,
               rotation_weight: ArrayLike, is_loop_closure: ArrayLike = False) -> slice:
        """Append many constraints (weights and the flag broadcast); return their index range."""
        submap = np.atleast_1d(np.asarray(submap, dtype=np.int64))
        k = len(submap)
        relative = np.asarray(relative, dtype=np.float64).reshape(k, 3)
        self._reserve(self._n + k)
        s = slice(self._n, self._n + k)
        self._submap[s] = submap
        self._node[s] = np.broadcast_to(np.asarray(node, dtype=np.int64), (k,))
        self._relative[s] = relative
        self._translation_weight[s] = np.broadcast_to(np.asarray(translation_weight, dtype=np.float64), (k,))
        self._rotation_weight[s] = np.broadcast_to(np.asarray(rotation_weight, dtype=np.float64), (k,))
        self._loop[s] = np.broadcast_to(np.asarray(is_loop_closure, dtype=bool), (k,))
        self._n += k
        return s

    # ------------------------------------------------------------------ columns

    @property
    def submap(self) -> np.ndarray:
        return self._submap[: self._n]

    @property
    def node(self) -> np.ndarray:
        return self._node[: self._n]

    @property
    def relative(self) -> np.ndarray:
        return self._relative[: self._n]

    @property
    def translation_weight(self) -> np.ndarray:
        return self._translation_weight[: self._n]

    @property
    def rotation_weight(self) -> np.ndarray:
        return self._rotation_weight[: self._n]

    @property
    def is_loop_closure(self) -> np.ndarray:
        return self._loop[: self._n]

    @property
    def num_loop_closures(self) -> int:
        return int(np.count_nonzero(self.is_loop_closure))

    # ------------------------------------------------------------------ access

    def __len__(self) -> int:
        return self._n

    def __getitem__(self, i: int) -> Constraint:
        i = range(self._n)[i]  # bounds check and negative indices
        return Constraint(int(self._submap[i]), int(self._node[i]), self._relative[i].copy(),
                          float(self._translation_weight[i]), float(self._rotation_weight[i]),
                          ConstraintKind.INTER_SUBMAP if self._loop[i] else ConstraintKind.INTRA_SUBMAP)

    def __iter__(self) -> Iterator[Constraint]:
        return (self[i] for i in range(self._n))

    def select(self, which: ArrayLike) -> ConstraintSet:
        """A new set holding the constraints picked by a boolean mask or index array."""
        which = np.asarray(which)
        if which.dtype == bool and len(which) != self._n:
            raise ValueError(f"mask of length {len(which)} for {self._n} constraints")
        return ConstraintSet.from_arrays(self.submap[which], self.node[which], self.relative[which],
                                         self.translation_weight[which], self.rotation_weight[which],
                                         self.is_loop_closure[which])

    def remove(self, mask: ArrayLike) -> int:
        """Drop the constraints where ``mask`` is true, in place; return how many went."""
        mask = np.asarray(mask, dtype=bool)
        if len(mask) != self._n:
            raise ValueError(f"mask of length {len(mask)} for {self._n} constraints")
        keep = ~mask
        kept = int(np.count_nonzero(keep))
        for name in self._COLUMNS:
            col = getattr(self, name)
            col[:kept] = col[: self._n][keep]
        removed = self._n - kept
        self._n = kept
        return removed

    def copy(self) -> ConstraintSet:
        return self.select(np.arange(self._n))

    def __repr__(self) -> str:
        return f"ConstraintSet({self._n} constraints, {self.num_loop_closures} loop closures)"
