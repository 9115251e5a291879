"""Contact points of a world, mapped to scene object indices (−1 = the floor)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Mapping, Sequence

import numpy as np

FLOOR = -1
#: Default |normal · y| above which a contact counts as a support (≈ 45°).
SUPPORT_MIN_VERTICAL = 0.7


@dataclass
class ContactSet:
    """K contact points, world frame, metres.

    index_a, index_b: (K,) object indices of the two bodies; ``index_b`` is −1 for the floor (the floor is
        always B), and for two objects ``index_a < index_b``.
    position_a, position_b: (K, 3) the contact point on A's and on B's surface.
    normal: (K, 3) unit contact normal *on B, pointing from B towards A* (pybullet's ``contactNormalOnB``);
        moving A along it separates the pair. An object on the floor has normal +y.
    distance: (K,) signed separation along the normal, negative when the bodies interpenetrate.
    normal_force: (K,) newtons, the normal force the solver applied in the last step (0 before any step).
    """

    index_a: np.ndarray
    index_b: np.ndarray
    position_a: np.ndarray
    position_b: np.ndarray
    normal: np.ndarray
    distance: np.ndarray
    normal_force: np.ndarray

    def __len__(self) -> int:
        return int(self.index_a.shape[0])

    @property
    def penetration(self) -> np.ndarray:
        """(K,) interpenetration depth, metres (max(−distance, 0))."""
        return np.maximum(-self.distance, 0.0)

    def pairs(self) -> np.ndarray:
        """(M, 2) distinct (a, b) index pairs in contact, sorted."""
        if len(self) == 0:
            return np.zeros((0, 2), np.int64)
        return np.unique(np.stack([self.index_a, self.index_b], 1), axis=0)

    def support_pairs(self, min_vertical: float = SUPPORT_MIN_VERTICAL) -> np.ndarray:
        """(M, 2) distinct (supporter, supported) pairs: the lower body supports the upper one.

        A contact is a support when its normal is within ``arccos(min_vertical)`` of vertical; the body the
        normal points towards is on top. The floor appears as supporter −1.
        """
        ny = self.normal[:, 1] if len(self) else np.zeros(0)
        up = ny >= min_vertical  # A on top of B
        down = ny <= -min_vertical  # B on top of A
        rows = np.concatenate([np.stack([self.index_b[up], self.index_a[up]], 1),
                               np.stack([self.index_a[down], self.index_b[down]], 1)])
        if len(rows) == 0:
            return np.zeros((0, 2), np.int64)
        return np.unique(rows.astype(np.int64), axis=0)


def contact_set(points: Sequence[tuple], index_of_body: Mapping[int, int]) -> ContactSet:
    """Build a :class:`ContactSet` from ``pybullet.getContactPoints`` tuples.

    ``index_of_body`` maps pybullet body ids to object indices (the floor's id to −1); points on other
    bodies are dropped. Pairs are reordered so the floor is B and otherwise ``index_a < index_b``.
    """
    ia, ib, pa, pb, nrm, dist, force = [], [], [], [], [], [], []
    for pt in points:
        a, b = index_of_body.get(pt[1]), index_of_body.get(pt[2])
        if a is None or b is None or a == b:
            continue
        pos_a, pos_b, n = pt[5], pt[6], np.asarray(pt[7], np.float64)
        if a == FLOOR or (b != FLOOR and a > b):
            a, b, pos_a, pos_b, n = b, a, pos_b, pos_a, -n
        ia.append(a)
        ib.append(b)
        pa.append(pos_a)
        pb.append(pos_b)
        nrm.append(n)
        dist.append(pt[8])
        force.append(pt[9])
    k = len(ia)
    return ContactSet(
        index_a=np.asarray(ia, np.int64), index_b=np.asarray(ib, np.int64),
        position_a=np.asarray(pa, np.float64).reshape(k, 3), position_b=np.asarray(pb, np.float64).reshape(k, 3),
        normal=np.asarray(nrm, np.float64).reshape(k, 3), distance=np.asarray(dist, np.float64),
        normal_force=np.asarray(force, np.float64),
    )
