"""3-D rendering of the integrated map (``map.png``; JP Figs. 12-13, thesis Figs. 6.12-6.13).

The scene: every cylinder segment as a truncated-cone tube (bark colour), the ground as the
0.6 m rendering grid of :func:`~forestmap_assets.core.features.elevation.render_grid` (mean of the 5
lowest
0.1 m cells) drawn as two triangles per cell and coloured by elevation with a labelled scale,
and every registered scan as a small coordinate frame (x red, y green, z blue; twice as large
at the reference scan) with its name.

Rendering is off-screen with VTK (pyvista). On a machine without a display, VTK's EGL window
(Mesa's software EGL works) is selected before the first window is made, so no X server is
needed; :func:`configure_offscreen` does that. When VTK cannot render at all, :func:`render_map`
falls back to a matplotlib 3-D picture of the same scene, so ``forestmap run`` never fails on
a picture.
"""

from __future__ import annotations

import os
import sys
from collections.abc import Sequence
from pathlib import Path

import numpy as np
import pandas as pd

BARK_RGB = (0.50, 0.30, 0.15)
GROUND_CMAP = "YlGn_r"  # lighter = higher, as in the thesis figures
SCAN_AXES = (
    ((1.0, 0.0, 0.0), "#d62728"),
    ((0.0, 1.0, 0.0), "#2ca02c"),
    ((0.0, 0.0, 1.0), "#1f77b4"),
)


def has_display() -> bool:
    """True when an interactive window can be opened (X11 / Wayland display, macOS, Windows)."""
    if sys.platform in ("darwin", "win32"):
        return True
    return bool(os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY"))


def configure_offscreen() -> bool:
    """Prepare VTK for off-screen rendering when there is no display; return ``has_display()``.

    Sets ``VTK_DEFAULT_OPENGL_WINDOW=vtkEGLRenderWindow`` (unless the user chose a window class)
    so that VTK does not try an X server first, and ``pyvista.OFF_SCREEN``."""
    display = has_display()
    if not display:
        os.environ.setdefault("VTK_DEFAULT_OPENGL_WINDOW", "vtkEGLRenderWindow")
        import pyvista as pv

        pv.OFF_SCREEN = True
    return display


# ------------------------------------------------------------------------------------------
# meshes


def _frames(axis: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Two unit vectors perpendicular to each unit ``axis`` (n, 3) and to each other."""
    helper = np.where(np.abs(axis[:, 2:3]) < 0.9, [[0.0, 0.0, 1.0]], [[1.0, 0.0, 0.0]])
    u = np.cross(axis, helper)
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    return u, np.cross(axis, u)


def tube_mesh_arrays(
    cylinders: pd.DataFrame, sides: int = 16
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Vertices (n * 2 * sides, 3), VTK face array and per-face cylinder index of truncated
    cones from ``(x0, y0, z0)`` radius ``r0_m`` to ``(x1, y1, z1)`` radius ``r1_m`` (``radius_m``
    when the end radii are absent), with closed ends (thesis 4.6.3 cylinder segment model)."""
    n = len(cylinders)
    if n == 0:
        return np.zeros((0, 3)), np.zeros(0, np.int64), np.zeros(0, np.int64)
    p0 = cylinders[["x0", "y0", "z0"]].to_numpy(float)
    p1 = cylinders[["x1", "y1", "z1"]].to_numpy(float)
    r0 = cylinders["r0_m" if "r0_m" in cylinders else "radius_m"].to_numpy(float)
    r1 = cylinders["r1_m" if "r1_m" in cylinders else "radius_m"].to_numpy(float)
    fallback = cylinders["radius_m"].to_numpy(float)
    r0 = np.where(np.isfinite(r0) & (r0 > 0), r0, fallback)
    r1 = np.where(np.isfinite(r1) & (r1 > 0), r1, fallback)
    axis = p1 - p0
    length = np.linalg.norm(axis, axis=1, keepdims=True)
    axis = np.where(length > 1e-9, axis / np.maximum(length, 1e-9), [[0.0, 0.0, 1.0]])
    u, v = _frames(axis)
    t = np.linspace(0.0, 2 * np.pi, sides, endpoint=False)
    ring = (
        np.cos(t)[None, :, None] * u[:, None, :] + np.sin(t)[None, :, None] * v[:, None, :]
    )  # (n, s, 3)
    bottom = p0[:, None, :] + r0[:, None, None] * ring
    top = p1[:, None, :] + r1[:, None, None] * ring
    verts = np.concatenate([bottom, top], axis=1).reshape(-1, 3)  # per cylinder: s bottom, s top
    base = (np.arange(n) * 2 * sides)[:, None]
    k = np.arange(sides)[None, :]
    a, b = base + k, base + (k + 1) % sides
    quads = np.stack([np.full_like(a, 4), a, b, b + sides, a + sides], axis=-1).reshape(-1, 5)
    caps_b = np.concatenate(
        [np.full((n, 1), sides), base + np.arange(sides)[::-1][None, :]], axis=1
    )
    caps_t = np.concatenate(
        [np.full((n, 1), sides), base + sides + np.arange(sides)[None, :]], axis=1
    )
    faces = np.concatenate([quads.ravel(), caps_b.ravel(), caps_t.ravel()]).astype(np.int64)
    owner = np.concatenate([np.repeat(np.arange(n), sides), np.arange(n), np.arange(n)])
    return verts, faces, owner


def cylinder_tubes(cylinders: pd.DataFrame, sides: int = 16):
    """The cylinder segments as one :class:`pyvista.PolyData` with a ``cylinder`` cell array."""
    import pyvista as pv

    verts, faces, owner = tube_mesh_arrays(cylinders, sides)
    mesh = pv.PolyData(verts, faces) if len(verts) else pv.PolyData()
    if len(verts):
        mesh.cell_data["cylinder"] = owner
    return mesh


def surface_arrays(grid) -> tuple[np.ndarray, np.ndarray]:
    """Vertices and triangles of an elevation grid drawn as two triangles per cell (spec 9,
    Figs. 6.12-6.13): vertices at the cell centres, a quad of four neighbouring centres split
    into two triangles wherever all four have a value."""
    z = grid.z
    if z.size == 0 or z.shape[0] < 2 or z.shape[1] < 2:
        return np.zeros((0, 3)), np.zeros((0, 3), np.int64)
    xs, ys = grid.centres()
    ny, nx = z.shape
    X, Y = np.meshgrid(xs, ys)
    verts = np.stack([X.ravel(), Y.ravel(), np.nan_to_num(z).ravel()], axis=1)
    ok = np.isfinite(z)
    quad = ok[:-1, :-1] & ok[1:, :-1] & ok[:-1, 1:] & ok[1:, 1:]
    jj, ii = np.nonzero(quad)
    v00 = jj * nx + ii
    v10, v01, v11 = v00 + 1, v00 + nx, v00 + nx + 1
    tris = np.concatenate([np.stack([v00, v10, v11], 1), np.stack([v00, v11, v01], 1)])
    return verts, tris


def ground_surface(
    grid, render_cell_m: float = 0.6, n_lowest: int = 5, spike_m: float | None = 1.0
):
    """The ground as a :class:`pyvista.PolyData` with an ``elevation_m`` point array, from the
    0.6 m rendering grid (mean of the ``n_lowest`` lowest fine cells, spec 9), spikes removed
    (:func:`remove_spikes`)."""
    import pyvista as pv

    from forestmap_assets.core.features.elevation import render_grid
    from forestmap_assets.outputs.figures.elevation import remove_spikes

    coarse = remove_spikes(render_grid(grid, render_cell_m, n_lowest), spike_m)
    verts, tris = surface_arrays(coarse)
    if len(tris) == 0:
        return pv.PolyData()
    faces = np.concatenate([np.full((len(tris), 1), 3), tris], axis=1).ravel()
    mesh = pv.PolyData(verts, faces).clean()
    mesh.point_data["elevation_m"] = mesh.points[:, 2]
    return mesh


def _registered(poses: pd.DataFrame | None) -> pd.DataFrame:
    if poses is None or len(poses) == 0:
        return pd.DataFrame(columns=["scan", "x", "y", "z", "heading_deg"])
    reg = poses["registered"]
    if reg.dtype != bool:
        reg = reg.astype(str).str.lower().isin(["true", "1"])
    return poses[reg.to_numpy(bool)]


# ------------------------------------------------------------------------------------------
# scene


def map_plotter(
    cylinders: pd.DataFrame,
    grid=None,
    poses: pd.DataFrame | None = None,
    *,
    title: str = "",
    views: Sequence[str] = ("bird", "top"),
    window_size: tuple[int, int] = (2000, 1000),
    off_screen: bool | None = None,
    margin_m: float = 4.0,
    clim: tuple[float, float] | None = None,
    reference: str | None = None,
    spike_m: float | None = 1.0,
    ground_cmap: str = GROUND_CMAP,
):
    """A :class:`pyvista.Plotter` with the integrated map, one sub-plot per view: ``"bird"``
    (oblique bird's-eye view, JP Fig. 13 / thesis Fig. 6.12), ``"top"`` (straight down, thesis
    Fig. 6.13), ``"side"`` (horizontal, from the south). The ground is cut to the box of the
    cylinders and scans plus ``margin_m`` (inferred: the far field holds only sparse rings);
    ``clim`` defaults to the 1st-99th percentile of the drawn ground. The top view is a parallel
    projection, so stems appear as their cross-sections (a stem map)."""
    display = configure_offscreen()  # before the first VTK window is made
    import pyvista as pv

    from forestmap_assets.outputs.figures.elevation import colour_limits, crop_box, crop_grid

    if off_screen is None:
        off_screen = not display
    placed = _registered(poses)
    tubes = cylinder_tubes(cylinders)
    ground = None
    if grid is not None and grid.z.size and np.isfinite(grid.z).any():
        pts = pd.concat(
            [cylinders[["x0", "y0"]].set_axis(["x", "y"], axis=1), placed[["x", "y"]]],
            ignore_index=True,
        )
        g = crop_grid(grid, crop_box(grid, pts, None, margin_m)) if len(pts) else grid
        ground = ground_surface(g, spike_m=spike_m)
        if clim is None and ground.n_points:
            clim = colour_limits(ground.points[:, 2])
    shape = (1, len(views))
    p = pv.Plotter(off_screen=off_screen, shape=shape, window_size=window_size, border=False)
    ref = (
        reference
        if reference is not None
        else (str(poses["scan"].iloc[0]) if poses is not None and len(poses) else None)
    )
    span = _span(tubes, ground, placed)
    for k, view in enumerate(views):
        p.subplot(0, k)
        p.set_background("white", top="#c9d9ec")
        with_bar = ground is not None and ground.n_points and k == len(views) - 1
        if ground is not None and ground.n_points:
            # the colour bar: under a top view (room is left below it), else upright on the right
            bar_args = (
                dict(
                    title="ground elevation z (m)",
                    vertical=False,
                    position_x=0.25,
                    position_y=0.08,
                    height=0.08,
                    width=0.5,
                )
                if view == "top"
                else dict(
                    title="ground z (m)",
                    vertical=True,
                    position_x=0.86,
                    position_y=0.2,
                    height=0.55,
                    width=0.06,
                )
            )
            p.add_mesh(
                ground,
                scalars="elevation_m",
                cmap=ground_cmap,
                clim=clim,
                show_edges=False,
                smooth_shading=True,
                ambient=0.25,
                show_scalar_bar=bool(with_bar),
                scalar_bar_args=dict(
                    fmt="%.1f",
                    n_labels=5,
                    color="black",
                    title_font_size=18,
                    label_font_size=15,
                    **bar_args,
                ),
            )
            if with_bar and view == "top":
                for bar in p.scalar_bars.values():
                    bar.SetTextPositionToPrecedeScalarBar()  # labels, then the title, below the bar
        if tubes.n_points:
            p.add_mesh(tubes, color=BARK_RGB, smooth_shading=True, specular=0.1, ambient=0.2)
        _add_scans(p, placed, 0.04 * span, ref, labels=True)
        _camera(p, view, room_below=0.12 if with_bar else 0.0)
        if with_bar and view != "top":
            p.camera.zoom(0.9)  # room for the upright colour bar
        label = {"bird": "bird's-eye view", "top": "from above", "side": "from the south"}.get(
            view, view
        )
        p.add_text(label, position="upper_right", font_size=11, color="black")
    if title:
        p.subplot(0, 0)
        p.add_text(title, position="upper_left", font_size=13, color="black")
    return p


def _span(tubes, ground, placed) -> float:
    boxes = []
    for mesh in (tubes, ground):
        if mesh is not None and mesh.n_points:
            b = np.asarray(mesh.bounds)
            boxes.append([b[0], b[1], b[2], b[3]])
    if len(placed):
        boxes.append([placed["x"].min(), placed["x"].max(), placed["y"].min(), placed["y"].max()])
    if not boxes:
        return 10.0
    b = np.asarray(boxes, dtype=float)
    return float(max(b[:, 1].max() - b[:, 0].min(), b[:, 3].max() - b[:, 2].min(), 1.0))


def _add_scans(
    p, placed: pd.DataFrame, length_m: float, reference: str | None, labels: bool
) -> None:
    """Scan frames: arrows along the scan's x (red), y (green) and z (blue) axes, one glyph mesh
    per axis over every scan (a mesh per arrow took 4 s for 51 scans)."""
    import pyvista as pv

    if not len(placed):
        return
    origins = placed[["x", "y", "z"]].to_numpy(float)
    size = np.where(placed["scan"].astype(str).to_numpy() == str(reference), 2 * length_m, length_m)
    h = np.radians(placed["heading_deg"].to_numpy(float))
    c, s = np.cos(h), np.sin(h)
    zero, one = np.zeros_like(h), np.ones_like(h)
    axes = {(1.0, 0.0, 0.0): np.column_stack([c, s, zero]), (0.0, 1.0, 0.0): np.column_stack([-s, c, zero]),
            (0.0, 0.0, 1.0): np.column_stack([zero, zero, one])}  # R_z(heading) of each axis
    arrow = pv.Arrow(tip_length=0.3, tip_radius=0.12, shaft_radius=0.045)  # unit length along x
    for direction, colour in SCAN_AXES:
        frame = pv.PolyData(origins)
        frame["direction"] = axes[direction]
        frame["size"] = size
        p.add_mesh(frame.glyph(orient="direction", scale="size", factor=1.0, geom=arrow), color=colour)
    centres = pv.PolyData(origins)
    centres["size"] = size
    p.add_mesh(centres.glyph(orient=False, scale="size", factor=1.0, geom=pv.Sphere(radius=0.12)), color="black")
    if labels and len(placed):
        pts = placed[["x", "y", "z"]].to_numpy(float) + np.array([0.0, 0.0, 1.3 * length_m])
        p.add_point_labels(
            pts,
            [str(s) for s in placed["scan"]],
            font_size=16,
            text_color="black",
            point_size=1,
            shape_opacity=0.6,
            shape_color="white",
            always_visible=True,
            show_points=False,
        )


def _camera(p, view: str, room_below: float = 0.0) -> None:
    """Standard views; ``room_below`` (share of the view height) is left free at the bottom of
    the top view for the colour bar."""
    if view == "top":
        p.view_xy()
        p.enable_parallel_projection()
        p.reset_camera()
        cam = p.camera
        cam.parallel_scale *= 0.92 + room_below / 2
        shift = cam.parallel_scale * room_below
        fx, fy, fz = cam.focal_point
        px, py, pz = cam.position
        cam.focal_point = (fx, fy - shift, fz)
        cam.position = (px, py - shift, pz)
        return
    elif view == "side":
        p.view_vector((0.0, -1.0, 0.12), viewup=(0.0, 0.0, 1.0))
    else:
        p.view_vector((-0.75, -1.0, 0.62), viewup=(0.0, 0.0, 1.0))
    p.reset_camera()
    p.camera.zoom(1.06)


def map_image(cylinders, grid=None, poses=None, **kwargs) -> np.ndarray:
    """The off-screen rendering as an RGB array (rows, cols, 3)."""
    p = map_plotter(cylinders, grid, poses, off_screen=True, **kwargs)
    try:
        img = p.screenshot(return_img=True)
    finally:
        p.close()
    return np.asarray(img)[..., :3]


def _blank(img: np.ndarray) -> bool:
    """True when a rendering shows nothing (every pixel the same colour): VTK silently failed."""
    flat = img.reshape(-1, img.shape[-1])
    return bool(flat.size == 0 or np.all(flat == flat[0]))


def render_map(
    path: str | os.PathLike,
    cylinders: pd.DataFrame,
    grid=None,
    poses: pd.DataFrame | None = None,
    *,
    title: str = "",
    fallback: bool = True,
    **kwargs,
) -> Path:
    """Write ``map.png`` (atomically): the pyvista scene of :func:`map_plotter`; with
    ``fallback`` a matplotlib 3-D picture when VTK cannot render here (:func:`save_map_mpl`)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    try:
        img = map_image(cylinders, grid, poses, title=title, **kwargs)
        if _blank(img):
            raise RuntimeError("VTK rendered an empty image")
    except Exception:
        if not fallback:
            raise
        return save_map_mpl(path, cylinders, grid, poses, title=title)
    from PIL import Image

    tmp = path.with_name(f".{path.name}.tmp-{os.getpid()}.png")
    try:  # light compression: a third of the default's time for a slightly larger file
        Image.fromarray(np.ascontiguousarray(img, dtype=np.uint8)).save(tmp, format="PNG", compress_level=2)
        os.replace(tmp, path)
    finally:
        if tmp.exists():
            tmp.unlink()
    return path


def save_map_mpl(path, cylinders: pd.DataFrame, grid=None, poses=None, *, title: str = "") -> Path:
    """``map.png`` as the matplotlib 3-D picture of :func:`map_figure_mpl` (VTK cannot render)."""
    from forestmap_assets.outputs.figures.common import save_png

    return save_png(map_figure_mpl(cylinders, grid, poses, title=title + " (matplotlib fallback)"), Path(path))


def map_figure_mpl(
    cylinders: pd.DataFrame,
    grid=None,
    poses: pd.DataFrame | None = None,
    *,
    title: str = "",
    margin_m: float = 4.0,
):
    """The same scene with matplotlib's 3-D axes (fallback when VTK cannot render): ground as
    a triangulated surface of the 0.6 m rendering grid, cylinders as thick lines, scan frames."""
    from forestmap_assets.core.features.elevation import render_grid
    from forestmap_assets.outputs.figures.common import new_figure
    from forestmap_assets.outputs.figures.elevation import crop_box, crop_grid, ground_limits

    fig = new_figure(10.0, 8.0)
    ax = fig.add_subplot(projection="3d")
    placed = _registered(poses)
    if grid is not None and grid.z.size and np.isfinite(grid.z).any():
        pts = pd.concat(
            [cylinders[["x0", "y0"]].set_axis(["x", "y"], axis=1), placed[["x", "y"]]],
            ignore_index=True,
        )
        g = crop_grid(grid, crop_box(grid, pts, None, margin_m)) if len(pts) else grid
        verts, tris = surface_arrays(render_grid(g))
        if len(tris):
            lo, hi = ground_limits(g)
            surf = ax.plot_trisurf(
                verts[:, 0],
                verts[:, 1],
                verts[:, 2],
                triangles=tris,
                cmap="viridis",
                vmin=lo,
                vmax=hi,
                linewidth=0,
                alpha=0.9,
            )
            fig.colorbar(surf, ax=ax, shrink=0.6, label="ground elevation (m)")
    for r in cylinders.itertuples(index=False):
        ax.plot(
            [r.x0, r.x1],
            [r.y0, r.y1],
            [r.z0, r.z1],
            color="#8c5a2b",
            lw=max(1.0, 40 * float(r.radius_m)),
        )
    for r in placed.itertuples(index=False):
        ax.scatter([r.x], [r.y], [r.z], color="black", s=20)
        ax.text(r.x, r.y, r.z + 0.5, str(r.scan))
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")
    ax.set_zlabel("z (m)")
    ax.set_aspect("equal")
    ax.view_init(elev=35, azim=-125)
    ax.set_title(title)
    return fig


def show_map(cylinders, grid=None, poses=None, *, interactive: bool | None = None, **kwargs):
    """In a notebook: an interactive pyvista view when a display exists (``interactive`` None;
    in Jupyter this needs pyvista's trame extra), else the static off-screen rendering as a
    matplotlib figure (returned)."""
    display = configure_offscreen()
    if interactive if interactive is not None else display:
        p = map_plotter(cylinders, grid, poses, off_screen=False, **kwargs)
        try:
            p.show()  # a VTK window, or trame in Jupyter
            return p
        except ImportError:  # Jupyter without trame: the static picture below
            p.close()
    from forestmap_assets.outputs.figures.common import new_figure

    img = map_image(cylinders, grid, poses, **kwargs)
    fig = new_figure(img.shape[1] / 160, img.shape[0] / 160, layout=None)
    ax = fig.add_axes((0, 0, 1, 1))
    ax.imshow(img)
    ax.set_axis_off()
    return fig
