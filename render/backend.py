"""Choice of the off-screen OpenGL back-end (EGL first, OSMesa as the fallback) for MuJoCo.

PyOpenGL fixes its platform (``PYOPENGL_PLATFORM``) the first time it is imported and MuJoCo reads
``MUJOCO_GL`` when it is imported, so one process can use one back-end only. ``auto`` therefore
probes each candidate in a short-lived subprocess (a failed EGL attempt in this process would leave
PyOpenGL unusable for OSMesa) and then commits this process, and its children, to the first one
that renders.
"""

from __future__ import annotations

import os
import subprocess
import sys

BACKENDS = ("egl", "osmesa")
_PROBE_TIMEOUT_S = 120.0

# Renders one frame of a one-box model off-screen; exits non-zero with the reason if it cannot.
_PROBE_CODE = """
import os, sys
backend = sys.argv[1]
os.environ["MUJOCO_GL"] = backend
os.environ["PYOPENGL_PLATFORM"] = backend
import importlib
import mujoco
import numpy as np
GLContext = importlib.import_module("mujoco." + backend).GLContext
ctx = GLContext(32, 32)
ctx.make_current()
model = mujoco.MjModel.from_xml_string(
    "<mujoco><worldbody><light dir='0 0 -1'/><geom type='box' size='1 1 1' rgba='1 0 0 1'/>"
    "<camera name='c' pos='0 0 5'/></worldbody></mujoco>")
data = mujoco.MjData(model)
mujoco.mj_forward(model, data)
con = mujoco.MjrContext(model, mujoco.mjtFontScale.mjFONTSCALE_100)
mujoco.mjr_setBuffer(mujoco.mjtFramebuffer.mjFB_OFFSCREEN, con)
scn = mujoco.MjvScene(model, maxgeom=10)
cam = mujoco.MjvCamera()
cam.type = mujoco.mjtCamera.mjCAMERA_FIXED
cam.fixedcamid = 0
mujoco.mjv_updateScene(model, data, mujoco.MjvOption(), None, cam, mujoco.mjtCatBit.mjCAT_ALL, scn)
rect = mujoco.MjrRect(0, 0, 32, 32)
mujoco.mjr_render(rect, scn, con)
rgb = np.zeros((32, 32, 3), np.uint8)
mujoco.mjr_readPixels(rgb, None, rect, con)
con.free()
ctx.free()
if rgb[16, 16, 0] < 50:
    sys.exit(f"rendered a wrong colour {rgb[16, 16].tolist()} (expected red)")
print("probe-ok")
"""

_chosen: str | None = None


class BackendError(RuntimeError):
    """No usable off-screen OpenGL back-end (the message names every failure)."""


def probe_backend(backend: str) -> str | None:
    """Try to render one frame with ``backend`` in a subprocess; None if it works, else the reason."""
    env = {k: v for k, v in os.environ.items() if k not in ("MUJOCO_GL", "PYOPENGL_PLATFORM")}
    try:
        proc = subprocess.run(
            [sys.executable, "-c", _PROBE_CODE, backend],
            env=env,
            capture_output=True,
            text=True,
            timeout=_PROBE_TIMEOUT_S,
        )
    except subprocess.TimeoutExpired:
        return f"probe timed out after {_PROBE_TIMEOUT_S:.0f} s"
    if proc.returncode == 0 and "probe-ok" in proc.stdout.split():
        return None
    tail = (proc.stderr or proc.stdout).strip().splitlines()[-3:]
    return f"exit code {proc.returncode}: " + " | ".join(tail)


def _validate(requested: str) -> str:
    requested = str(requested).lower().strip()
    if requested not in ("auto", *BACKENDS):
        raise ValueError(f"render.backend must be one of auto, {', '.join(BACKENDS)}; got {requested!r}")
    return requested


def _committed_platform() -> str | None:
    """The back-end this process is already tied to (PyOpenGL imported), or None while still free."""
    if "OpenGL" in sys.modules or "OpenGL.platform" in sys.modules:
        platform = os.environ.get("PYOPENGL_PLATFORM", "").lower()
        return platform or "unknown"
    return None


def select_backend(requested: str = "auto") -> str:
    """Choose the back-end for this process and set ``MUJOCO_GL``/``PYOPENGL_PLATFORM`` for it.

    Args:
        requested: ``auto`` (EGL, else OSMesa; a ``MUJOCO_GL`` already set to one of them is tried
            first), ``egl`` or ``osmesa``.

    Returns:
        ``"egl"`` or ``"osmesa"``.

    Raises:
        ValueError: ``requested`` is not a known back-end.
        BackendError: no candidate renders, or this process is already tied to another back-end.
    """
    global _chosen
    requested = _validate(requested)
    if _chosen is not None:
        if requested not in ("auto", _chosen):
            raise BackendError(
                f"this process already renders with {_chosen!r}; render.backend={requested!r} needs a new "
                "process (the OpenGL platform is fixed per process)"
            )
        return _chosen

    committed = _committed_platform()
    if requested == "auto":
        env_choice = os.environ.get("MUJOCO_GL", "").lower()
        candidates = [env_choice] if env_choice in BACKENDS else []
        candidates += [b for b in BACKENDS if b not in candidates]
    else:
        candidates = [requested]
    if committed is not None:
        if committed not in BACKENDS or (requested != "auto" and committed != requested):
            raise BackendError(
                f"PyOpenGL was imported in this process with PYOPENGL_PLATFORM={committed!r} before the "
                f"renderer chose its back-end (render.backend={requested!r}); import render before "
                "anything that imports OpenGL, or set MUJOCO_GL/PYOPENGL_PLATFORM to egl or osmesa"
            )
        candidates = [committed]

    failures = {}
    for backend in candidates:
        reason = probe_backend(backend)
        if reason is None:
            os.environ["MUJOCO_GL"] = backend
            os.environ["PYOPENGL_PLATFORM"] = backend
            _chosen = backend
            return backend
        failures[backend] = reason
    detail = "; ".join(f"{b}: {r}" for b, r in failures.items())
    raise BackendError(
        f"no off-screen OpenGL back-end works (render.backend={requested!r}). {detail}. "
        "EGL needs libEGL + Mesa (apt: libegl1 libgl1-mesa-dri), OSMesa needs libosmesa6."
    )


def gl_context_class(backend: str):
    """MuJoCo's ``GLContext`` class for a back-end chosen by ``select_backend``."""
    if backend == "egl":
        # heavy (mujoco): imported on use
        from mujoco.egl import GLContext
    elif backend == "osmesa":
        # heavy (mujoco): imported on use
        from mujoco.osmesa import GLContext
    else:
        raise ValueError(f"unknown back-end {backend!r}")
    return GLContext
