"""Walking paths over the grid (men_spec 3.6, 7.4-7.5): navigable cells (G cells and the walked
discs under the
scan positions, ``obstacle_clearance_m`` from any O cell), the 8-connected graph with Euclidean step
costs,
Dijkstra distances and predecessors to every cell, and A* with the octile heuristic."""

from __future__ import annotations

import heapq

import numpy as np
from scipy import ndimage
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import dijkstra

from forestmap_assets.core.exploration.frontier import GROUND, OBSTACLE
from forestmap_assets.core.exploration.grid import ExplorationGrid

# ---- paths -----------------------------------------------------------------------------------
_STEPS = np.array([[1, 0], [0, 1], [1, 1], [1, -1]])


def navigable_cells(
    classes: np.ndarray,
    cell_m: float,
    *,
    obstacle_clearance_m: float = 0.5,
    walked: np.ndarray | None = None,
) -> np.ndarray:
    """Cells one may walk through (nx, ny): G cells and ``walked`` cells (the blind discs under the
    scan positions: the operator stood there) at least ``obstacle_clearance_m`` from any O cell
    (men_spec 3.6 robot footprint; inferred for a surveyor with a tripod)."""
    free = classes == GROUND
    if walked is not None:
        free |= walked & (classes != OBSTACLE)
    k = int(np.ceil(obstacle_clearance_m / cell_m - 1e-9))
    if k > 0:
        off = np.arange(-k, k + 1)
        disc = (
            np.hypot(*np.meshgrid(off, off, indexing="ij")) * cell_m <= obstacle_clearance_m + 1e-9
        )
        blocked = ndimage.binary_dilation(classes == OBSTACLE, structure=disc)
    else:
        blocked = classes == OBSTACLE
    return free & ~blocked


def grid_graph(nav: np.ndarray, cell_m: float) -> coo_matrix:
    """8-connected graph of navigable cells, Euclidean step costs; a diagonal step needs both
    orthogonal neighbours navigable (no corner cutting, inferred)."""
    nx, ny = nav.shape
    rows, cols, w = [], [], []
    for dx, dy in _STEPS:
        x0, x1 = max(0, -dx), nx - max(0, dx)
        y0, y1 = max(0, -dy), ny - max(0, dy)
        a = nav[x0:x1, y0:y1]
        b = nav[x0 + dx : x1 + dx, y0 + dy : y1 + dy]
        ok = a & b
        if dx and dy:
            ok &= nav[x0 + dx : x1 + dx, y0:y1] & nav[x0:x1, y0 + dy : y1 + dy]
        ia, ja = np.nonzero(ok)
        src = (ia + x0) * ny + (ja + y0)
        dst = (ia + x0 + dx) * ny + (ja + y0 + dy)
        rows += [src, dst]
        cols += [dst, src]
        w += [np.full(2 * src.size, cell_m * np.hypot(dx, dy))]
    n = nx * ny
    if not rows:
        return coo_matrix((n, n))
    return coo_matrix(
        (np.concatenate(w), (np.concatenate(rows), np.concatenate(cols))), shape=(n, n)
    )


def path_distances(
    nav: np.ndarray, start: tuple[int, int], cell_m: float
) -> tuple[np.ndarray, np.ndarray]:
    """Shortest walking distance (nx, ny; inf = unreachable) from ``start`` to every cell and the
    predecessor of each cell on its shortest path (-9999 none): Dijkstra, i.e. A* to every goal
    (men_spec 7.4)."""
    nav = nav.copy()
    nav[start] = True
    graph = grid_graph(nav, cell_m).tocsr()
    src = start[0] * nav.shape[1] + start[1]
    dist, pred = dijkstra(graph, directed=False, indices=src, return_predecessors=True)
    return dist.reshape(nav.shape), pred


def path_from(pred: np.ndarray, goal: tuple[int, int], shape: tuple[int, int]) -> np.ndarray:
    """Cells ``(k, 2)`` of the shortest path from the start to ``goal`` (from predecessors)."""
    ny = shape[1]
    node = int(goal[0]) * ny + int(goal[1])
    out = [node]
    while pred[node] >= 0:
        node = int(pred[node])
        out.append(node)
    out = np.array(out[::-1])
    return np.column_stack([out // ny, out % ny])


def astar(
    nav: np.ndarray, start: tuple[int, int], goal: tuple[int, int], cell_m: float = 1.0
) -> tuple[np.ndarray, float]:
    """A* path (cells ``(k, 2)``) and length over 8-connected navigable cells with the octile
    heuristic (men_spec 7.4-7.5); empty path and inf when the goal cannot be reached."""
    nx, ny = nav.shape
    nav = nav.copy()
    nav[start] = True
    goal = (int(goal[0]), int(goal[1]))
    if not nav[goal]:
        return np.zeros((0, 2), dtype=int), np.inf

    def h(c):
        dx, dy = abs(c[0] - goal[0]), abs(c[1] - goal[1])
        return cell_m * (max(dx, dy) + (np.sqrt(2) - 1) * min(dx, dy))

    start = (int(start[0]), int(start[1]))
    g = {start: 0.0}
    came: dict = {}
    heap = [(h(start), 0.0, start)]
    done = set()
    while heap:
        _, gc, c = heapq.heappop(heap)
        if c in done:
            continue
        if c == goal:
            path = [c]
            while c in came:
                c = came[c]
                path.append(c)
            return np.array(path[::-1]), gc
        done.add(c)
        for dx in (-1, 0, 1):
            for dy in (-1, 0, 1):
                if not (dx or dy):
                    continue
                n = (c[0] + dx, c[1] + dy)
                if not (0 <= n[0] < nx and 0 <= n[1] < ny) or not nav[n] or n in done:
                    continue
                if dx and dy and not (nav[c[0] + dx, c[1]] and nav[c[0], c[1] + dy]):
                    continue
                ng = gc + cell_m * (np.sqrt(2) if dx and dy else 1.0)
                if ng < g.get(n, np.inf):
                    g[n] = ng
                    came[n] = c
                    heapq.heappush(heap, (ng + h(n), ng, n))
    return np.zeros((0, 2), dtype=int), np.inf


def walked_cells(grid: ExplorationGrid, scan_xy: np.ndarray, radius_m: float) -> np.ndarray:
    """Cells within ``radius_m`` of a scan position (the blind disc under the scanner)."""
    xc, yc = grid.centres()
    out = np.zeros(grid.shape, dtype=bool)
    for x, y in np.asarray(scan_xy, dtype=np.float64).reshape(-1, 2):
        out |= np.hypot(xc[:, None] - x, yc[None, :] - y) <= radius_m
    return out
