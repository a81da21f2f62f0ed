"""An interactive 3-D view of a plan as ONE self-contained HTML file (opens offline in any browser).

    uavplan view outputs/tomb/ours/default/seed0/2026-11-23_06-00-00 --out plan.html

shows the viewpoints (coloured by kind, hover for index, pose and kind), each camera's frustum
(from the run's intrinsics), the trajectory in flight order and the ground-truth or proxy mesh,
decimated to a size a browser handles. plotly.js is embedded in the file: no network, no install.
"""

from __future__ import annotations

import argparse
import logging
import sys
from collections.abc import Sequence
from pathlib import Path

import numpy as np
import trimesh

from experiments.flight_figures import decimate_mesh, kind_colour
from experiments.runs import (
    METRICS_FILE,
    Run,
    RunDirectoryError,
    read_metrics,
    read_run_viewpoints,
    run_intrinsics,
    run_scene_mesh,
)
from scene.camera import Intrinsics, validate_viewpoint_array, world_from_cam_rotation
from scene.io import write_text_atomic

log = logging.getLogger(__name__)


def frustum_corners(viewpoints: np.ndarray, intrinsics: Intrinsics, depth_m: float) -> np.ndarray:
    """World positions (V, 4, 3) in metres of the image corners of each camera at ``depth_m`` along its axis.

    Corners in image order: top-left, top-right, bottom-right, bottom-left (pixel (0, 0) is top-left).
    """
    vps = validate_viewpoint_array(viewpoints)
    if not depth_m > 0:
        raise ValueError(f"frustum depth must be positive, got {depth_m} m")
    w, h = float(intrinsics.width), float(intrinsics.height)
    pixels = np.array([[0.0, 0.0], [w, 0.0], [w, h], [0.0, h]])
    rays_cam = np.column_stack(
        [
            (pixels[:, 0] - intrinsics.cx) / intrinsics.focal_px,
            (pixels[:, 1] - intrinsics.cy) / intrinsics.focal_px,
            np.ones(4),
        ]
    )
    world_from_cam = world_from_cam_rotation(vps[:, 3], vps[:, 4])  # (V, 3, 3)
    return vps[:, None, :3] + depth_m * np.einsum("vij,cj->vci", world_from_cam, rays_cam)


def frustum_polylines(viewpoints: np.ndarray, corners: np.ndarray) -> np.ndarray:
    """Every frustum edge as one (N, 3) polyline with NaN rows between strokes (plotly's line breaks).

    Per camera: the image rectangle, the edges from the camera centre to the four corners, and a
    short tick on the top edge's midpoint so the image's up direction can be told apart.
    """
    apex = np.asarray(viewpoints, dtype=float)[:, None, :3]
    c = corners
    gap = np.full((len(c), 1, 3), np.nan)
    top_mid = 0.5 * (c[:, 0] + c[:, 1])
    up_tick = top_mid + 0.15 * (c[:, 0] - c[:, 3])
    strokes = np.concatenate(
        [
            c[:, [0, 1, 2, 3, 0]],
            apex,
            c[:, [2]],
            gap,
            c[:, [1]],
            apex,
            c[:, [3]],
            gap,
            top_mid[:, None],
            up_tick[:, None],
            gap,
        ],
        axis=1,
    )
    return strokes.reshape(-1, 3)


# WebGL renderers without 32-bit indices (SwiftShader, some mobile GPUs) draw garbage for meshes with
# more vertices than a 16-bit index reaches: keep the mesh below that.
MAX_BROWSER_VERTICES = 65_000


def browser_mesh(mesh, max_faces: int = 60_000):
    """``mesh`` with duplicate vertices merged, at most ``max_faces`` triangles and fewer than
    ``MAX_BROWSER_VERTICES`` vertices (quadric decimation where needed)."""
    merged = trimesh.Trimesh(np.asarray(mesh.vertices), np.asarray(mesh.faces), process=True)
    target = int(max_faces)
    while True:
        small = decimate_mesh(merged, target)
        if len(small.vertices) < MAX_BROWSER_VERTICES or target <= 4:
            return small
        target = max(4, int(target * 0.9 * MAX_BROWSER_VERTICES / len(small.vertices)))


def _rounded(values: np.ndarray) -> list:
    # Lists (not arrays) so plotly writes plain JSON numbers a reader can find in the file; NaN -> None.
    return [None if not np.isfinite(v) else round(float(v), 4) for v in np.asarray(values, dtype=float)]


def build_plan_figure(
    viewpoints: np.ndarray,
    kinds: Sequence[str],
    intrinsics: Intrinsics | None,
    mesh=None,
    mesh_label: str = "mesh",
    frustum_depth_m: float | None = None,
    title: str = "",
):
    """A plotly figure of a plan: mesh, trajectory, one viewpoint trace and one frustum trace per kind.

    Args:
        viewpoints: (V, 5) ``x, y, z, yaw_deg, pitch_deg`` in flight order (metres, degrees).
        kinds: V viewpoint kinds.
        intrinsics: the camera (None: no frusta).
        mesh: a ``trimesh.Trimesh`` (already decimated) or None.
        mesh_label: legend name of the mesh.
        frustum_depth_m: frustum length along the optical axis in metres (default: 5 % of the
            extent of viewpoints and mesh).
        title: figure title.

    Returns:
        ``plotly.graph_objects.Figure``; the viewpoint trace of kind ``k`` is named ``k`` and holds
        the positions as plain lists (rounded to 0.1 mm).
    """
    # heavy (plotly): imported on use
    import plotly.graph_objects as go

    vps = validate_viewpoint_array(viewpoints)
    kinds = list(kinds)
    if len(kinds) != len(vps):
        raise ValueError(f"{len(kinds)} kinds for {len(vps)} viewpoints")
    points = vps[:, :3] if mesh is None else np.vstack([vps[:, :3], np.asarray(mesh.vertices)])
    diagonal = float(np.linalg.norm(points.max(axis=0) - points.min(axis=0))) or 1.0
    depth = frustum_depth_m if frustum_depth_m is not None else 0.05 * diagonal

    fig = go.Figure()
    if mesh is not None and len(mesh.faces):
        vertices = np.asarray(mesh.vertices, dtype=np.float32)
        faces = np.asarray(mesh.faces, dtype=np.int32)
        fig.add_trace(
            go.Mesh3d(
                x=vertices[:, 0],
                y=vertices[:, 1],
                z=vertices[:, 2],
                i=faces[:, 0],
                j=faces[:, 1],
                k=faces[:, 2],
                color="rgb(214,210,200)",
                opacity=1.0,
                # Smooth shading shares vertices; flat shading triples them and hits the limit below.
                flatshading=False,
                name=mesh_label,
                showlegend=True,
                hoverinfo="skip",
                # plotly's default light sits on the horizon, which leaves roofs and ground black.
                lighting={"ambient": 0.45, "diffuse": 0.65, "specular": 0.05, "roughness": 0.9},
                lightposition={"x": 3e4, "y": 5e4, "z": 1e5},
            )
        )
    fig.add_trace(
        go.Scatter3d(
            x=_rounded(vps[:, 0]),
            y=_rounded(vps[:, 1]),
            z=_rounded(vps[:, 2]),
            mode="lines",
            name="trajectory",
            line={"color": "rgb(90,90,90)", "width": 2},
            hoverinfo="skip",
        )
    )
    seen = list(dict.fromkeys(kinds))
    kinds_arr = np.array(kinds)
    for kind in seen:
        index = np.flatnonzero(kinds_arr == kind)
        colour = kind_colour(kind, seen)
        sel = vps[index]
        hover = [
            f"#{i} {kind}<br>x {v[0]:.2f} y {v[1]:.2f} z {v[2]:.2f} m<br>yaw {v[3]:.1f}° pitch {v[4]:.1f}°"
            for i, v in zip(index, sel, strict=True)
        ]
        fig.add_trace(
            go.Scatter3d(
                x=_rounded(sel[:, 0]),
                y=_rounded(sel[:, 1]),
                z=_rounded(sel[:, 2]),
                mode="markers",
                name=kind,
                legendgroup=kind,
                marker={"size": 3.5, "color": colour},
                text=hover,
                hoverinfo="text",
                customdata=index.tolist(),
            )
        )
        if intrinsics is not None:
            lines = frustum_polylines(sel, frustum_corners(sel, intrinsics, depth))
            fig.add_trace(
                go.Scatter3d(
                    x=_rounded(lines[:, 0]),
                    y=_rounded(lines[:, 1]),
                    z=_rounded(lines[:, 2]),
                    mode="lines",
                    name=f"{kind} frusta",
                    legendgroup=kind,
                    showlegend=False,
                    hoverinfo="skip",
                    line={"color": colour, "width": 1.5},
                    connectgaps=False,
                )
            )
    fig.update_layout(
        title=title,
        scene={"aspectmode": "data", "xaxis_title": "x (m)", "yaxis_title": "y (m)", "zaxis_title": "z (m)"},
        legend={"itemsizing": "constant"},
        margin={"l": 0, "r": 0, "t": 40 if title else 0, "b": 0},
    )
    return fig


def write_viewer(
    run_dir: str | Path,
    out: str | Path | None = None,
    mesh_source: str = "ground_truth",
    max_faces: int = 60_000,
    frustum_depth_m: float | None = None,
    intrinsics: Intrinsics | None = None,
) -> Path:
    """Write the self-contained HTML view of the plan in ``run_dir``; return its path.

    Args:
        run_dir: a run directory with ``plan/viewpoints.csv``.
        out: HTML file (default ``<run_dir>/plan.html``).
        mesh_source: ``ground_truth``, ``proxy`` or ``none`` (falls back to the other mesh if absent).
        max_faces: triangles kept of the mesh.
        frustum_depth_m: frustum length in metres (default: 5 % of the scene's extent).
        intrinsics: the camera; default: the run's (``.hydra/config.yaml`` camera or ``plan.json``).

    Raises:
        RunDirectoryError: ``run_dir`` has no plan.
    """
    run_dir = Path(run_dir)
    if not run_dir.is_dir():
        raise RunDirectoryError(f"run directory not found: {run_dir}")
    plan = read_run_viewpoints(run_dir)
    if plan is None:
        raise RunDirectoryError(f"{run_dir} has no plan/viewpoints.csv")
    viewpoints, kinds = plan
    metrics = read_metrics(run_dir) if (run_dir / METRICS_FILE).is_file() else {}
    intrinsics = intrinsics or run_intrinsics(run_dir)
    if intrinsics is None:
        log.warning("%s records no camera (.hydra/config.yaml or plan.json): no frusta drawn", run_dir)
    mesh, label = None, ""
    if mesh_source != "none":
        mesh, label = run_scene_mesh(Run(run_dir, metrics), prefer=mesh_source)
        mesh = browser_mesh(mesh, max_faces) if mesh is not None else None
    title = " / ".join(str(metrics[k]) for k in ("scene", "planner") if metrics.get(k))
    title = f"{title}: {len(viewpoints)} viewpoints" if title else f"{len(viewpoints)} viewpoints"
    fig = build_plan_figure(viewpoints, kinds, intrinsics, mesh, label or "mesh", frustum_depth_m, title)
    html = fig.to_html(include_plotlyjs=True, full_html=True, config={"displaylogo": False})
    out = Path(out) if out is not None else run_dir / "plan.html"
    return write_text_atomic(out, html)


def main(argv: Sequence[str] | None = None) -> int:
    """Command line: ``uavplan view RUN_DIR [--out plan.html]``; returns the exit status."""
    parser = argparse.ArgumentParser(prog="uavplan view", description=__doc__.split("\n")[0])
    parser.add_argument("run_dir", type=Path, help="a run directory (with plan/viewpoints.csv)")
    parser.add_argument("--out", type=Path, help="HTML file to write (default: RUN_DIR/plan.html)")
    parser.add_argument("--mesh", choices=("ground_truth", "proxy", "none"), default="ground_truth")
    parser.add_argument("--max-faces", type=int, default=60_000, help="triangles kept of the mesh")
    parser.add_argument(
        "--frustum-depth", type=float, help="frustum length in metres (default: 5%% of the scene)"
    )
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(levelname)s %(message)s")
    try:
        path = write_viewer(args.run_dir, args.out, args.mesh, args.max_faces, args.frustum_depth)
    except (RunDirectoryError, ValueError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    print(f"{path} ({path.stat().st_size / 1e6:.1f} MB): open it in a browser")
    return 0


if __name__ == "__main__":
    sys.exit(main())
