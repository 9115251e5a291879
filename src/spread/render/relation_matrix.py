"""The paper's relation matrix: for every ordered object pair, does the scene's pose realise its graph's relation?

Row i, column j is the pair "i is … of j" (DESIGN §3's spatial codes). ``expected`` is the scene's
``spatial`` matrix — for a generated scene, the conditioning graph it was sampled from; ``found`` is
recomputed from the posed meshes by :func:`spread.relations.scene_spatial_codes`, the one implementation that
GRecall uses too, so the green cells of a scene are exactly the pairs GRecall counts as matching
(:func:`spread.metrics.scene_graph_recall`): a cell is green (:data:`MATCH`) where found == expected, red
(:data:`MISMATCH`) where not, grey (:data:`SELF`) on the diagonal.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

#: Cell colours (RGB): relation realised, relation missed, the diagonal.
MATCH = (46, 160, 67)
MISMATCH = (214, 39, 40)
SELF = (200, 200, 200)

#: One-letter names of the spatial codes 0..5 for cell text (U: under = below; B: behind).
CODE_LETTERS = ("R", "L", "F", "B", "A", "U")
CODE_KEY = "R right of, L left of, F in front of, B behind, A above, U under (below)"


@dataclass
class RelationAgreement:
    """expected (N, N): the graph's codes; found (N, N): codes of the poses; labels: ``"i category"``."""

    scene_id: str
    expected: np.ndarray
    found: np.ndarray
    labels: list[str]

    @property
    def match(self) -> np.ndarray:
        """(N, N) bool: off-diagonal pairs whose found code equals the graph's (False on the diagonal)."""
        return (self.found == self.expected) & ~np.eye(len(self.labels), dtype=bool)

    @property
    def pairs(self) -> int:
        n = len(self.labels)
        return n * (n - 1)

    @property
    def matches(self) -> int:
        return int(self.match.sum())

    @property
    def recall(self) -> float:
        return self.matches / self.pairs if self.pairs else float("nan")


def relation_agreement(scene, library) -> RelationAgreement:
    """The agreement of ``scene``'s poses with its own ``spatial`` graph (module docstring)."""
    from spread.relations import scene_spatial_codes

    found = scene_spatial_codes(scene.translation, scene.rotation, [str(a) for a in scene.asset_id], library)
    labels = [f"{i} {c}" for i, c in enumerate(scene.category)]
    return RelationAgreement(scene.scene_id, np.asarray(scene.spatial, np.int8).copy(), np.asarray(found, np.int8),
                             labels)


def agreement_colours(agreement: RelationAgreement) -> np.ndarray:
    """(N, N, 3) uint8 cell colours: :data:`MATCH`, :data:`MISMATCH`, :data:`SELF` on the diagonal."""
    n = len(agreement.labels)
    out = np.empty((n, n, 3), np.uint8)
    out[:] = MISMATCH
    out[agreement.match] = MATCH
    out[np.arange(n), np.arange(n)] = SELF
    return out
