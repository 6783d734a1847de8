"""The numpy kd-tree builder's references (core/accel/kdtree.py): one row of float32 words per
reference, moved between nodes by whole-row gathers (docs/kdtree.md)."""
from __future__ import annotations

import numpy as np

# A reference is one row of 7 float32 words: box lo (3), box hi (3), triangle id (int32 bits),
# so that moving references is one gather of 28-byte rows instead of three gathers.
REF_WORDS = 7
_REF_ROW = np.dtype((np.void, 4 * REF_WORDS))
BOX_ROW = np.dtype((np.void, 4 * 6))


def gather_refs(refs: np.ndarray, index: np.ndarray) -> np.ndarray:
    """Rows `index` of the (N, 7) float32 reference array, as one gather of whole rows."""
    rows = np.take(refs.view(_REF_ROW).reshape(-1), index.reshape(-1))
    return rows.view(np.float32).reshape(index.shape + (REF_WORDS,))


def ref_triangles(refs: np.ndarray) -> np.ndarray:
    return refs[:, 6].view(np.int32)

