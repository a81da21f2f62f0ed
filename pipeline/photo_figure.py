"""``flight.png``: what a crew checks before flying a plan made from its photos.

Left, from above: the proxy (its vertices, coloured by height above take-off), the exploratory
photos where their GNSS put them (registered: dots; left out by SfM: red crosses), the planned
flight in order (line) and its waypoints (coloured by height), the take-off point. Right, from the
side (east against height): the same flight against the drone's floor and ceiling.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np


def write_flight_figure(path: Path, proxy, flight, plan, registered: set[str], report: dict) -> Path:
    """Draw ``path`` (PNG) from the proxy (``pipeline.proxy.Proxy`` or a mesh), the exploratory
    ``flight`` (``reconstruct.flight.Flight``), the ``plan`` and the names SfM registered."""
    # heavy (matplotlib): imported on use
    import matplotlib

    matplotlib.use("Agg")
    # heavy (matplotlib): imported on use
    import matplotlib.pyplot as plt

    mesh = getattr(proxy, "mesh", proxy)
    vertices = np.asarray(mesh.vertices)
    rng = np.random.default_rng(0)
    if len(vertices) > 30000:
        vertices = vertices[rng.choice(len(vertices), 30000, replace=False)]
    photos = flight.positions
    ok = np.array([n in registered for n in flight.names])
    vps = np.asarray(plan.viewpoints)
    limits = report.get("waypoints", {})
    ceiling, floor = limits.get("ceiling_m"), limits.get("floor_m")

    fig, (top, side) = plt.subplots(1, 2, figsize=(14, 6.5), gridspec_kw={"width_ratios": [1.2, 1]})
    top.scatter(vertices[:, 0], vertices[:, 1], c=vertices[:, 2], s=1, cmap="Greys", alpha=0.5)
    top.plot(vps[:, 0], vps[:, 1], "-", color="tab:blue", lw=0.6, alpha=0.6, label="planned flight (order)")
    points = top.scatter(vps[:, 0], vps[:, 1], c=vps[:, 2], s=14, cmap="viridis", zorder=3)
    fig.colorbar(points, ax=top, label="waypoint height above take-off (m)", shrink=0.8)
    top.scatter(
        photos[ok, 0],
        photos[ok, 1],
        marker="o",
        s=22,
        facecolors="none",
        edgecolors="k",
        label=f"exploratory photos, registered ({int(ok.sum())})",
    )
    if (~ok).any():
        top.scatter(
            photos[~ok, 0],
            photos[~ok, 1],
            marker="x",
            s=40,
            color="red",
            label=f"photos not registered ({int((~ok).sum())})",
        )
    takeoff = vps[0, :2]
    top.scatter(
        [takeoff[0]],
        [takeoff[1]],
        marker="*",
        s=180,
        color="orange",
        edgecolors="k",
        zorder=4,
        label="take-off (ground under waypoint 1)",
    )
    top.set_aspect("equal")
    top.set_xlabel("east (m)")
    top.set_ylabel("north (m)")
    top.legend(loc="upper left", fontsize=8)
    top.set_title("from above: proxy, photos, plan")

    side.scatter(vertices[:, 0], vertices[:, 2], s=1, color="0.6", alpha=0.4)
    side.plot(vps[:, 0], vps[:, 2], "o", ms=3, color="tab:blue", label="waypoints")
    side.plot(photos[:, 0], photos[:, 2], "ko", ms=4, mfc="none", label="exploratory photos")
    if ceiling is not None:
        side.axhline(ceiling, color="red", ls="--", lw=1, label=f"ceiling {ceiling:g} m")
    if floor is not None:
        side.axhline(floor, color="orange", ls=":", lw=1, label=f"floor {floor:g} m")
    side.axhline(0.0, color="k", lw=0.5)
    side.set_xlabel("east (m)")
    side.set_ylabel("height above take-off (m)")
    side.legend(loc="upper left", fontsize=8)
    side.set_title("from the side: heights")

    reg = report.get("registration", {})
    plan_record = report.get("plan", {})
    fig.suptitle(
        f"{report.get('photos', {}).get('camera', '')}: {reg.get('n_registered')} of "
        f"{report.get('photos', {}).get('n_photos')} photos registered, GNSS residual median "
        f"{(reg.get('gnss_residual_median_m') or float('nan')):.2f} m; plan {len(vps)} views, "
        f"{vps[:, 2].min():.0f}-{vps[:, 2].max():.0f} m, {plan_record.get('flight_time_s', 0) / 60:.1f} min, "
        f"{plan_record.get('n_batteries', '?')} batteries",
        fontsize=10,
    )
    fig.tight_layout()
    path = Path(path)
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path
