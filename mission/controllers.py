"""Waypoints a controller app accepts in one mission file, and which app flies a given drone.

A mission longer than its app accepts is split into numbered files, one flight each
(``drone.model.split_flights``). The caps, per app:

- ``fly``: DJI Fly on the RC 2 / RC-N (Mini, Air, Mavic consumer bodies, sideloaded WPML): users
  report it crashing when a mission holds more than 99 waypoints (YLabs-FPV/YMapper issue 8), so 99;
- ``pilot2``: DJI Pilot 2 (enterprise bodies: Matrice, Mavic 3 Enterprise, Phantom 4 RTK): the WPML
  format takes 2 to 65535 waypoints (DJI's SDK), and this project's missions were flown at 200
  (``drone.max_waypoints_per_file``): 200;
- ``litchi``: Litchi Mission Hub's CSV, 99 waypoints per mission (``mission.litchi``);
- ``qgc``: QGroundControl writes three items per waypoint (gimbal, waypoint, photo); ArduPilot on a
  Pixhawk-class board stores 724 mission items (PX4 stores more): 240 waypoints.

``plan-photos`` chooses the DJI app from the camera's EXIF model (``photos.controller: auto``) and
writes every format with its own app's cap; ``photos.max_waypoints`` caps them all.
"""

from __future__ import annotations

CAPS: dict[str, int] = {"fly": 99, "pilot2": 200, "litchi": 99, "qgc": 240}
# EXIF Model prefixes of DJI's enterprise bodies (flown with DJI Pilot 2, or GS RTK for the P4 RTK):
# Mavic 3 Enterprise (M3E, M3T, M3M), Matrice 30 (M30, M30T), Zenmuse payloads (ZH20*, XT2, P1, L1),
# Phantom 4 RTK / Multispectral (FC6310R, FC6360).
ENTERPRISE_MODELS = (
    "M3E",
    "M3T",
    "M3M",
    "M30",
    "M3D",
    "M4E",
    "M4T",
    "ZH20",
    "ZENMUSE",
    "XT2",
    "P1",
    "L1",
    "L2",
    "FC6310R",
    "FC6360",
    "MAVIC3E",
)


class ControllerError(ValueError):
    """An unknown controller name or a cap that is not a positive number (one line naming it)."""


def dji_app(camera: str) -> str:
    """The DJI app that flies the drone of a photo's ``"Make Model"`` (EXIF): ``pilot2`` for an
    enterprise body, else ``fly``."""
    model = camera.split(" ", 1)[-1].replace(" ", "").upper()
    return "pilot2" if any(model.startswith(m.upper()) for m in ENTERPRISE_MODELS) else "fly"


def caps_for(camera: str, controller: str = "auto", max_waypoints: int | None = None) -> dict[str, int]:
    """Waypoints per file for each mission format (``qgc``, ``litchi``, ``wpml``) of a drone whose
    photos say ``camera``.

    Args:
        controller: ``auto`` (WPML for the DJI app of ``dji_app``), or the app that flies the WPML
            missions: ``pilot2`` or ``fly`` (``litchi`` and ``qgc`` keep their own caps).
        max_waypoints: a cap on every format (None: the apps' own).

    Raises:
        ControllerError: an unknown ``controller`` or a cap below 2.
    """
    if controller == "auto":
        wpml_app = dji_app(camera)
    elif controller in ("pilot2", "fly"):
        wpml_app = controller
    elif controller in ("litchi", "qgc"):
        wpml_app = "fly" if dji_app(camera) == "fly" else "pilot2"
    else:
        raise ControllerError(f"photos.controller={controller!r}: expected auto, pilot2, fly, litchi or qgc")
    caps = {"qgc": CAPS["qgc"], "litchi": CAPS["litchi"], "wpml": CAPS[wpml_app]}
    if max_waypoints is not None:
        if int(max_waypoints) < 2:
            raise ControllerError(f"photos.max_waypoints={max_waypoints!r}: a mission needs at least 2")
        caps = {fmt: min(cap, int(max_waypoints)) for fmt, cap in caps.items()}
    return caps
