"""Maze layouts: grids of wall cells turned into world geometry.

A layout is a grid of characters, ``"1"`` for a wall block, ``"0"`` for a free cell, ``"r"`` for the start
cell and ``"g"`` for the goal cell (both free). Cell ``(row i, column j)`` is centred at
``(j * scale - x0, i * scale - y0)`` where ``(x0, y0)`` puts the start cell at the origin: columns map to x
and rows to y. Wall blocks are boxes of the cell size, ``wall_height * scale`` tall. Extra walls (the
bottleneck's thin walls) are given as explicit boxes.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

__all__ = [
    "WallBox",
    "MazeLayout",
    "U_MAZE",
    "COMPLEX_MAZE",
    "BOTTLENECK_WALL_FRICTION",
    "bottleneck_walls",
]

#: The U-shaped maze of AntMazeSmall, AntMaze, AntMazeBottleneck and PointMaze.
U_MAZE = (
    "11111",
    "1r001",
    "11101",
    "1g001",
    "11111",
)

#: The 9 x 9 maze of AntMazeComplex.
COMPLEX_MAZE = (
    "111111111",
    "1r0010g01",
    "111010001",
    "100011011",
    "101110011",
    "101010111",
    "100000101",
    "101010001",
    "111111111",
)


@dataclass(frozen=True)
class WallBox:
    """An axis-aligned wall box.

    Args:
        center (tuple of float): ``(x, y, z)`` centre of the box.
        half_size (tuple of float): ``(hx, hy, hz)`` half sizes.
        friction (tuple of float, optional): MuJoCo geom friction; ``None`` keeps the model default.

    Examples:
        >>> from torchrl_dhrl.envs import WallBox
        >>> box = WallBox(center=(13.5, 8.0, 4.0), half_size=(1.9, 1.0, 4.0))
        >>> box.xy_bounds
        (11.6, 15.4, 7.0, 9.0)
    """

    center: tuple[float, float, float]
    half_size: tuple[float, float, float]
    friction: tuple[float, float, float] | None = None

    @property
    def xy_bounds(self) -> tuple[float, float, float, float]:
        """``(x_min, x_max, y_min, y_max)`` of the box footprint."""
        (cx, cy, _), (hx, hy, _) = self.center, self.half_size
        return (round(cx - hx, 12), round(cx + hx, 12), round(cy - hy, 12), round(cy + hy, 12))


#: Friction (slide, torsion, roll) of all 20 walls of the reference's ``ant_maze_bottleneck.xml``: the 18 blocks
#: and the two thin walls.
BOTTLENECK_WALL_FRICTION = (2.0, 0.1, 0.002)


def bottleneck_walls(
    friction: tuple[float, float, float] = BOTTLENECK_WALL_FRICTION,
) -> tuple[WallBox, WallBox]:
    """The two thin walls of AntMazeBottleneck in the corridor cell centred at (16, 8).

    They leave the gap ``15.4 < x < 17.0`` (1.6 wide) through which an ant barely passes.

    Args:
        friction (tuple of float): friction of the two walls. Defaults to ``(2, 0.1, 0.002)``.

    Examples:
        >>> from torchrl_dhrl.envs import bottleneck_walls
        >>> [wall.xy_bounds[:2] for wall in bottleneck_walls()]
        [(11.6, 15.4), (17.0, 20.0)]
    """
    return (
        WallBox(center=(13.5, 8.0, 4.0), half_size=(1.9, 1.0, 4.0), friction=friction),
        WallBox(center=(18.5, 8.0, 4.0), half_size=(1.5, 1.0, 4.0), friction=friction),
    )


@dataclass(frozen=True)
class MazeLayout:
    """World geometry of a grid maze.

    Args:
        grid (tuple of str): rows of ``"1"`` (wall), ``"0"`` (free), ``"r"`` (start), ``"g"`` (goal cell).
            All rows have the same length and exactly one ``"r"`` is present.
        scale (float): cell size in world units.
        wall_height (float): wall height as a fraction of ``scale``. Defaults to ``0.5``.
        extra_walls (tuple of WallBox): walls added on top of the grid blocks. Defaults to none.
        wall_friction (tuple of float, optional): MuJoCo friction of the grid blocks (an extra wall keeps its
            own); ``None`` (the default) gives them the scene's contact friction (the agent's).

    Examples:
        >>> from torchrl_dhrl.envs import MazeLayout, U_MAZE
        >>> layout = MazeLayout(U_MAZE, scale=4.0)
        >>> layout.bounds
        (array([-2., -2.]), array([10., 10.]))
        >>> layout.cell_center(3, 1).tolist()  # the goal cell
        [0.0, 8.0]
        >>> layout.in_wall([[4.0, 4.0], [8.0, 4.0]]).tolist()
        [True, False]
    """

    grid: tuple[str, ...]
    scale: float
    wall_height: float = 0.5
    extra_walls: tuple[WallBox, ...] = field(default_factory=tuple)
    wall_friction: tuple[float, float, float] | None = None

    def __post_init__(self) -> None:
        if len({len(row) for row in self.grid}) != 1:
            raise ValueError(f"All rows of the maze grid must have the same length, got {self.grid}.")
        chars = set("".join(self.grid))
        if not chars <= set("10rg"):
            raise ValueError(f"Maze grid characters must be in '10rg', got {sorted(chars)}.")
        if "".join(self.grid).count("r") != 1:
            raise ValueError("The maze grid must contain exactly one start cell 'r'.")
        if self.scale <= 0:
            raise ValueError(f"scale must be positive, got {self.scale}.")

    @property
    def walls(self) -> np.ndarray:
        """Boolean ``[rows, cols]`` array, ``True`` on wall cells."""
        return np.array([[char == "1" for char in row] for row in self.grid])

    @property
    def shape(self) -> tuple[int, int]:
        """``(rows, cols)`` of the grid."""
        return len(self.grid), len(self.grid[0])

    def _find(self, char: str) -> tuple[int, int] | None:
        for i, row in enumerate(self.grid):
            if char in row:
                return i, row.index(char)
        return None

    @property
    def start_cell(self) -> tuple[int, int]:
        """``(row, col)`` of the start cell."""
        return self._find("r")

    @property
    def goal_cell(self) -> tuple[int, int] | None:
        """``(row, col)`` of the goal cell, if the grid marks one."""
        return self._find("g")

    @property
    def origin_offset(self) -> np.ndarray:
        """``(x0, y0)`` subtracted from raw cell coordinates so that the start cell sits at the origin."""
        i, j = self.start_cell
        return np.array([j * self.scale, i * self.scale])

    def cell_center(self, row, col) -> np.ndarray:
        """World ``(x, y)`` of cell centres; ``row`` and ``col`` broadcast (arrays or ints)."""
        row, col = np.broadcast_arrays(np.asarray(row), np.asarray(col))
        xy = np.stack([col * self.scale, row * self.scale], axis=-1).astype(np.float64)
        return xy - self.origin_offset

    def cell_index(self, xy) -> np.ndarray:
        """Integer ``[..., 2]`` ``(row, col)`` of the cells containing the points ``xy [..., 2]``."""
        raw = (np.asarray(xy, dtype=np.float64) + self.origin_offset) / self.scale
        col_row = np.floor(raw + 0.5).astype(np.int64)
        return col_row[..., ::-1]

    def in_free_cell(self, xy) -> np.ndarray:
        """Whether each point of ``xy [..., 2]`` lies in a non-wall grid cell (extra walls ignored)."""
        index = self.cell_index(xy)
        rows, cols = self.shape
        inside = (index[..., 0] >= 0) & (index[..., 0] < rows) & (index[..., 1] >= 0) & (index[..., 1] < cols)
        walls = self.walls
        row = np.clip(index[..., 0], 0, rows - 1)
        col = np.clip(index[..., 1], 0, cols - 1)
        return inside & ~walls[row, col]

    @property
    def wall_boxes(self) -> tuple[WallBox, ...]:
        """Every wall: one block per wall cell, then the extra walls."""
        half = self.scale / 2
        half_height = self.wall_height * self.scale / 2
        rows, cols = np.nonzero(self.walls)
        centers = self.cell_center(rows, cols)
        blocks = tuple(
            WallBox(
                center=(float(x), float(y), half_height),
                half_size=(half, half, half_height),
                friction=self.wall_friction,
            )
            for x, y in centers
        )
        return blocks + tuple(self.extra_walls)

    def in_wall(self, xy, margin: float = 0.0) -> np.ndarray:
        """Whether each point of ``xy [..., 2]`` lies inside a wall footprint grown by ``margin``.

        Inside means in the interior of the union of the (grown) wall boxes: points on a face that
        borders free space count as outside, points on a face shared by two adjacent wall blocks
        (e.g. the middle of the U-maze's inner wall) as inside.
        """
        xy = np.asarray(xy, dtype=np.float64)
        bounds = np.array([box.xy_bounds for box in self.wall_boxes])  # [W, 4]

        def closed(points: np.ndarray) -> np.ndarray:
            x, y = points[..., 0, None], points[..., 1, None]
            return (
                (x >= bounds[:, 0] - margin)
                & (x <= bounds[:, 1] + margin)
                & (y >= bounds[:, 2] - margin)
                & (y <= bounds[:, 3] + margin)
            ).any(axis=-1)

        # interior of the union: the point and every point a hair away from it are in a closed box
        eps = 1e-9 * max(1.0, float(np.abs(bounds).max()))
        steps = np.array([(dx, dy) for dx in (-1, 0, 1) for dy in (-1, 0, 1)], dtype=np.float64) * eps
        return np.stack([closed(xy + step) for step in steps]).all(axis=0)

    @property
    def bounds(self) -> tuple[np.ndarray, np.ndarray]:
        """``(low, high)`` corners of the bounding box of the free cells (the arena inside the outer walls)."""
        rows, cols = np.nonzero(~self.walls)
        centers = self.cell_center(rows, cols)
        half = self.scale / 2
        return centers.min(axis=0) - half, centers.max(axis=0) + half

    @property
    def extent(self) -> tuple[np.ndarray, np.ndarray]:
        """``(low, high)`` corners of the whole grid, walls included."""
        rows, cols = self.shape
        corners = self.cell_center(np.array([0, rows - 1]), np.array([0, cols - 1]))
        half = self.scale / 2
        return corners[0] - half, corners[1] + half
