"""A cloud's structure seen from above, on a grid of cells: to compare a heading search's
overlays cheaply.

The heading search may offer several overlays of two clouds (a square courtyard overlays
almost as well turned by 90 degrees), each a metre and a few degrees off. Telling them apart
needs only whether each occupied cell of one cloud lands next to an occupied cell of the
other: a look-up in a grid, not a nearest-neighbour search over every point.
"""

from __future__ import annotations

import numpy as np
from scipy.ndimage import binary_dilation


class PlanView:
    """The occupied ``cell`` x ``cell`` columns of ``structure`` ((N, 2+) points, x and y used)."""

    def __init__(self, structure: np.ndarray, cell: float) -> None:
        self.cell = float(cell)
        index = np.floor(np.asarray(structure)[:, :2] / self.cell).astype(np.int64)
        if len(index) == 0:
            self.centres = np.empty((0, 2))
            self._origin, self._near = np.zeros(2, dtype=np.int64), np.zeros((1, 1), dtype=bool)
            return
        # one empty cell around the occupied ones, which the dilation marks; cells beyond it are
        # two or more from any occupied one
        self._origin = index.min(axis=0) - 1
        grid = np.zeros(tuple(index.max(axis=0) - self._origin + 2), dtype=bool)
        grid[tuple((index - self._origin).T)] = True
        #: (M, 2) the centres of the occupied cells
        self.centres = (np.argwhere(grid) + self._origin + 0.5) * self.cell
        self._near = binary_dilation(grid, structure=np.ones((3, 3), dtype=bool))

    def near(self, xy: np.ndarray) -> np.ndarray:
        """(N,) bool: each (x, y) (this cloud's frame) lies in an occupied cell or one beside it."""
        index = np.floor(np.asarray(xy)[:, :2] / self.cell).astype(np.int64) - self._origin
        inside = np.all((index >= 0) & (index < self._near.shape), axis=1)
        found = np.zeros(len(index), dtype=bool)
        found[inside] = self._near[index[inside, 0], index[inside, 1]]
        return found
