"""Flight figures: a plan's viewpoints over the structure, in 3-D and from above, coloured by the kind
of view (one colour per kind in every figure) and marked by planner; the mesh decimated for drawing.
``experiments.figures`` assembles them with the metric plots and error panels."""

from __future__ import annotations

from collections.abc import Sequence

import matplotlib

matplotlib.use("Agg")

import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
import trimesh
from matplotlib.figure import Figure  # noqa: E402
from mpl_toolkits.mplot3d.art3d import Poly3DCollection  # noqa: E402

from scene.camera import forward_vectors  # noqa: E402

# Fixed colours for the viewpoint kinds the planners emit, so a kind looks the same in every figure.
KIND_COLOURS = {
    "detail": "#d62728",
    "coverage": "#1f77b4",
    "grid": "#2ca02c",
    "oblique": "#ff7f0e",
    "nadir": "#9467bd",
    "exploration": "#8c564b",
}
_SPARE_COLOURS = ("#e377c2", "#17becf", "#bcbd22", "#7f7f7f", "#393b79", "#637939")
METHOD_MARKERS = {"ours": "o", "ours_plus": "P", "smith": "s", "yan": "^", "lawnmower": "D"}
_SPARE_MARKERS = ("v", "P", "X", "*", "<", ">")
# Longest error image shown in a panel, in inches (keeps a panel of many views printable).


def _style(name: str, fixed: dict, spare: Sequence[str], known: Sequence[str]) -> str:
    """``fixed[name]``, or for a name without one the spare styles in order of ``known``."""
    if name in fixed:
        return fixed[name]
    others = [k for k in known if k not in fixed]
    index = others.index(name) if name in others else len(others)
    return spare[index % len(spare)]


def kind_colour(kind: str, known: Sequence[str] = ()) -> str:
    """Colour of a viewpoint kind; kinds without a fixed colour take spare ones in order of ``known``."""
    return _style(kind, KIND_COLOURS, _SPARE_COLOURS, known)


def method_marker(planner: str, known: Sequence[str] = ()) -> str:
    """Scatter marker of a planner (``ours`` a circle, ``smith`` a square, ...)."""
    return _style(planner, METHOD_MARKERS, _SPARE_MARKERS, known)


def decimate_mesh(mesh, max_faces: int):
    """``mesh`` with at most ``max_faces`` triangles (quadric decimation; unchanged if already small).

    Args:
        mesh: a ``trimesh.Trimesh``.
        max_faces: the largest triangle count to keep (>= 4).
    """
    if max_faces < 4:
        raise ValueError(f"max_faces must be at least 4, got {max_faces}")
    if len(mesh.faces) <= max_faces:
        return mesh
    # heavy (open3d): imported on use
    import open3d as o3d

    o3d_mesh = o3d.geometry.TriangleMesh(
        o3d.utility.Vector3dVector(np.asarray(mesh.vertices, dtype=float)),
        o3d.utility.Vector3iVector(np.asarray(mesh.faces, dtype=np.int32)),
    )
    simple = o3d_mesh.simplify_quadric_decimation(target_number_of_triangles=int(max_faces))
    faces = np.asarray(simple.triangles)
    if len(faces) == 0 or len(faces) > max_faces:
        # Quadric decimation can fail on degenerate input; a random subset still shows the shape.
        rng = np.random.default_rng(0)
        keep = np.sort(rng.choice(len(mesh.faces), size=max_faces, replace=False))
        return trimesh.Trimesh(mesh.vertices, mesh.faces[keep], process=False)
    return trimesh.Trimesh(np.asarray(simple.vertices), faces, process=False)


def _flight_extent(viewpoints: np.ndarray, mesh) -> tuple[np.ndarray, np.ndarray]:
    points = viewpoints[:, :3] if mesh is None else np.vstack([viewpoints[:, :3], np.asarray(mesh.vertices)])
    return points.min(axis=0), points.max(axis=0)


def _check_plan(viewpoints, kinds) -> tuple[np.ndarray, list[str]]:
    viewpoints = np.asarray(viewpoints, dtype=float).reshape(-1, 5)
    kinds = list(kinds)
    if len(kinds) != len(viewpoints):
        raise ValueError(f"{len(kinds)} kinds for {len(viewpoints)} viewpoints")
    return viewpoints, kinds


def _flight_geometry(viewpoints, kinds, mesh, arrow_length_m: float | None):
    """Validated plan, positions (V, 3), viewing arrows (V, 3) in metres and the (lo, hi, span) extent.

    The arrows are 4 % of the extent of flight and mesh long unless ``arrow_length_m`` is given.
    """
    viewpoints, kinds = _check_plan(viewpoints, kinds)
    lo, hi = _flight_extent(viewpoints, mesh)
    span = np.maximum(hi - lo, 1e-6)
    if arrow_length_m is None:
        arrow_length_m = 0.04 * float(np.linalg.norm(span))
    directions = forward_vectors(viewpoints[:, 3], viewpoints[:, 4]) * arrow_length_m
    return viewpoints, kinds, viewpoints[:, :3], directions, (lo, hi, span)


def draw_flight_3d(ax, viewpoints, kinds, mesh=None, arrow_length_m: float | None = None, mesh_label="scene"):
    """Draw a flight on a 3-D axes: light mesh, trajectory, one scatter and one quiver per kind.

    Args:
        ax: a matplotlib 3-D axes.
        viewpoints: (V, 5) ``x, y, z, yaw_deg, pitch_deg`` in flight order (metres, degrees).
        kinds: V viewpoint kinds.
        mesh: a ``trimesh.Trimesh`` (decimated) or None.
        arrow_length_m: arrow length in metres (default: 4 % of the extent of flight and mesh).
        mesh_label: label of the mesh collection.
    """
    viewpoints, kinds, positions, directions, (lo, hi, span) = _flight_geometry(
        viewpoints, kinds, mesh, arrow_length_m
    )
    if mesh is not None and len(mesh.faces):
        triangles = np.asarray(mesh.vertices)[np.asarray(mesh.faces)]
        # Lambertian grey under a light from the upper south-west, so walls and roofs read apart.
        light = np.array([-0.4, -0.6, 1.0]) / np.linalg.norm([-0.4, -0.6, 1.0])
        normals = np.cross(triangles[:, 1] - triangles[:, 0], triangles[:, 2] - triangles[:, 0])
        normals /= np.maximum(np.linalg.norm(normals, axis=1, keepdims=True), 1e-12)
        grey = 0.5 + 0.4 * np.abs(normals @ light)
        colours = np.column_stack([grey, grey, grey, np.full(len(grey), 0.45)])
        surface = Poly3DCollection(triangles, facecolors=colours, edgecolor="none", label=mesh_label)
        surface.set_rasterized(True)  # keeps the PDF small for meshes of thousands of triangles
        ax.add_collection3d(surface)
    ax.plot(*positions.T, color="0.35", linewidth=0.7, label="trajectory")
    seen = list(dict.fromkeys(kinds))
    kinds_arr = np.array(kinds)
    for kind in seen:
        mask = kinds_arr == kind
        colour = kind_colour(kind, seen)
        ax.scatter(
            *positions[mask].T, color=colour, s=14, depthshade=False, label=f"{kind} ({int(mask.sum())})"
        )
        ax.quiver(
            *positions[mask].T, *directions[mask].T, color=colour, linewidth=0.6, arrow_length_ratio=0.3
        )
    z_lo = min(lo[2], 0.0)
    ax.set_xlim(lo[0], hi[0])
    ax.set_ylim(lo[1], hi[1])
    ax.set_zlim(z_lo, hi[2])
    ax.set_box_aspect((span[0], span[1], max(hi[2] - z_lo, 1e-6)))
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")
    ax.set_zlabel("z (m)")
    ax.view_init(elev=30, azim=-60)


def draw_flight_top(ax, viewpoints, kinds, mesh=None, arrow_length_m: float | None = None):
    """Draw a flight seen from above (x right, y up): mesh shaded by height, trajectory, scatter and
    arrows (the horizontal part of each viewing direction) per kind. Arguments as ``draw_flight_3d``."""
    viewpoints, kinds, positions, directions, (lo, hi, span) = _flight_geometry(
        viewpoints, kinds, mesh, arrow_length_m
    )
    if mesh is not None and len(mesh.faces):
        vertices, faces = np.asarray(mesh.vertices), np.asarray(mesh.faces)
        heights = vertices[faces, 2].mean(axis=1)
        # Draw the highest triangles last so the roof covers the walls.
        order = np.argsort(heights)
        ax.tripcolor(
            vertices[:, 0],
            vertices[:, 1],
            faces[order],
            facecolors=heights[order],
            cmap="Greys",
            alpha=0.45,
            edgecolors="none",
            linewidth=0.0,
            antialiased=False,
            rasterized=True,
            zorder=0,
        )
    ax.plot(positions[:, 0], positions[:, 1], color="0.35", linewidth=0.7, label="trajectory", zorder=1)
    seen = list(dict.fromkeys(kinds))
    kinds_arr = np.array(kinds)
    for kind in seen:
        mask = kinds_arr == kind
        colour = kind_colour(kind, seen)
        label = f"{kind} ({int(mask.sum())})"
        ax.scatter(positions[mask, 0], positions[mask, 1], color=colour, s=14, label=label, zorder=3)
        ax.quiver(
            positions[mask, 0],
            positions[mask, 1],
            directions[mask, 0],
            directions[mask, 1],
            color=colour,
            angles="xy",
            scale_units="xy",
            scale=1.0,
            width=0.002,
            zorder=2,
        )
    ax.set_aspect("equal")
    margin = 0.05 * span[:2]
    ax.set_xlim(lo[0] - margin[0], hi[0] + margin[0])
    ax.set_ylim(lo[1] - margin[1], hi[1] + margin[1])
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")


def plot_flight_path(
    viewpoints: np.ndarray,
    kinds: Sequence[str],
    mesh=None,
    title: str = "",
    arrow_length_m: float | None = None,
    mesh_label: str = "scene",
) -> Figure:
    """A flight over the scene: 3-D view (left) and top view (right).

    Args:
        viewpoints: (V, 5) ``x, y, z, yaw_deg, pitch_deg`` in flight order (metres, degrees).
        kinds: V viewpoint kinds; each kind is one scatter (labelled with its count).
        mesh: a ``trimesh.Trimesh`` drawn light under the flight (decimate it first), or None.
        title: figure title.
        arrow_length_m: length of the viewing-direction arrows in metres (default: 4 % of the
            extent of viewpoints and mesh).
        mesh_label: legend label of the mesh.

    Returns:
        The figure: ``axes[0]`` is 3-D, ``axes[1]`` the top view (x right, y up); each holds one
        scatter per kind in order of first appearance.
    """
    fig = plt.figure(figsize=(13.0, 5.6))
    grid = fig.add_gridspec(1, 2, wspace=0.3)
    ax3d = fig.add_subplot(grid[0, 0], projection="3d")
    ax_top = fig.add_subplot(grid[0, 1])
    draw_flight_3d(ax3d, viewpoints, kinds, mesh, arrow_length_m, mesh_label)
    draw_flight_top(ax_top, viewpoints, kinds, mesh, arrow_length_m)
    ax_top.set_title("top view")
    ax_top.legend(loc="upper left", bbox_to_anchor=(1.01, 1.0), fontsize=8, frameon=False)
    if title:
        fig.suptitle(title)
    return fig


def plot_flight_paths_by_scene(flights: Sequence[tuple], title: str = "") -> Figure:
    """The paper's Figure 4: one 3-D flight per scene side by side.

    Args:
        flights: ``(subtitle, viewpoints (V, 5), kinds, mesh or None)`` per panel, in order.
        title: figure title.

    Returns:
        The figure; ``axes[i]`` is the 3-D view of ``flights[i]``.
    """
    if not flights:
        raise ValueError("no flights to draw")
    fig = plt.figure(figsize=(5.0 * len(flights), 5.0))
    for i, (subtitle, viewpoints, kinds, mesh) in enumerate(flights):
        ax = fig.add_subplot(1, len(flights), i + 1, projection="3d")
        draw_flight_3d(ax, viewpoints, kinds, mesh)
        ax.set_title(subtitle)
        ax.legend(loc="upper left", fontsize=7, frameon=False)
    if title:
        fig.suptitle(title)
    fig.tight_layout()
    return fig
