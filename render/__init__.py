"""MuJoCo off-screen rendering (EGL, OSMesa fallback) of a scene from a list of viewpoints.

Importing this package does not import MuJoCo: the OpenGL back-end must be chosen first
(``render.backend.select_backend``), which ``SceneRenderer`` and ``render_flight`` do.
"""

from render.backend import BackendError, select_backend
from render.flight import RenderResult, image_name, render_flight
from render.renderer import SceneRenderer
from render.settings import RenderSettings

__all__ = [
    "BackendError",
    "RenderResult",
    "RenderSettings",
    "SceneRenderer",
    "image_name",
    "render_flight",
    "select_backend",
]
