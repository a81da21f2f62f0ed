"""MuJoCo off-screen rendering (EGL, OSMesa fallback) of a scene from a list of viewpoints.

Importing this package does not import MuJoCo: the OpenGL back-end must be chosen first
(``render.backend.select_backend``), which ``SceneRenderer`` and ``render_flight`` do.
"""

from render.backend import BackendError, select_backend
from render.flight import CAMERAS_FILE, CameraRecord, RenderResult, image_name, read_cameras, render_flight
from render.renderer import SceneRenderer

__all__ = [
    "CAMERAS_FILE",
    "BackendError",
    "CameraRecord",
    "RenderResult",
    "SceneRenderer",
    "image_name",
    "read_cameras",
    "render_flight",
    "select_backend",
]
