"""Does a plan's forecast stereo support on the proxy's walls separate the flights the matcher does?

    python -m archive.wall_support CACHE_ENTRY RUN [RUN ...]

CACHE_ENTRY is the exploration cache entry the runs planned on (``cache/exploration/<key>``); each
RUN a run directory (``.hydra/config.yaml``, ``plan/viewpoints.csv``). On ours' planning samples of
that proxy (``n_points``, seed 0) and its coverage visibility, every plan's views get their forecast
stereo partners (``planner.ours.stereo_partners.partner_matrix``, ours' default rule). A view supports a
wall sample (normal within 45 deg of horizontal) when it sees it and one of its partners does too,
at a disparity gradient of at most G there (the two views' distances from the sample's tangent
plane differ by at most that share of the view's). Prints, per run and G, the share of wall samples
with three or more supporting views (fusion's ``min_num_pixels``) and the mean. The answer is in
results/planner_ours.md.
"""

import sys
from pathlib import Path

import numpy as np
import pandas as pd
from omegaconf import OmegaConf

from experiments.depth_errors import WALL_MAX_NORMAL_Z
from pipeline.proxy import load_proxy
from pipeline.settings import cell_settings
from planner.ours.ours import resolve_params
from planner.ours.ours_settings import OursSettings
from planner.ours.stereo_partners import partner_matrix
from planner.sampling import sample_surface
from planner.visibility import VisibilityModel

GRADIENTS = (None, 0.5, 0.3, 0.2)


def ours_visibility(proxy, run: Path):
    """Ours' settings, planning samples (points, normals) and coverage visibility on ``proxy``, with
    the camera and scene of ``run`` (whatever planner it flew)."""
    cfg = OmegaConf.load(run / ".hydra" / "config.yaml")
    cfg.planner = OmegaConf.load(Path("conf") / "planner" / "ours.yaml")
    cells = cell_settings(cfg)
    params = resolve_params(OmegaConf.to_container(cells.planner_params, resolve=True))
    settings = OursSettings.build(params, cells.intrinsics)
    samples, normals = sample_surface(proxy, settings.n_points, 0)
    vis = params["visibility"]
    model = VisibilityModel(
        proxy,
        samples,
        normals,
        cells.intrinsics,
        settings.det_limits,
        vis["ray_offset_m"],
        vis["image_margin_px"],
    ).with_limits(settings.cov_limits)
    return settings, samples, normals, model


def main() -> None:
    proxy = load_proxy(Path(sys.argv[1]))
    runs = [Path(a) for a in sys.argv[2:]]
    settings, samples, normals, model = ours_visibility(proxy, runs[0])
    wall = np.abs(normals[:, 2]) < WALL_MAX_NORMAL_Z
    for run in runs:
        vps = pd.read_csv(run / "plan" / "viewpoints.csv")[["x", "y", "z", "yaw_deg", "pitch_deg"]].to_numpy()
        obs = model.observe(vps)
        eligible = partner_matrix(obs.visible, obs.direction, vps, settings.partners)
        plane = np.abs(np.einsum("vpk,pk->vp", samples[None] - vps[:, None, :3], normals))
        line = [f"{run} ({len(vps)} views)"]
        for limit in GRADIENTS:
            support = np.zeros(obs.visible.shape, bool)
            for a in range(len(vps)):
                mates = np.flatnonzero(eligible[a])
                both = obs.visible[a][None] & obs.visible[mates]
                if limit is not None:
                    both &= np.abs(plane[mates] - plane[a]) <= limit * plane[a]
                support[a] = both.any(axis=0)
            n = support.sum(axis=0)[wall]
            line.append(f"G {limit}: {100 * np.mean(n >= 3):.1f} % (mean {n.mean():.1f})")
        print(" | ".join(line), flush=True)


if __name__ == "__main__":
    main()
