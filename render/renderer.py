"""An off-screen MuJoCo renderer of one scene for one camera, reused across many viewpoints."""

from __future__ import annotations

import numpy as np

from render.backend import gl_context_class, select_backend
from render.model import BuiltModel, build_model
from render.settings import RenderSettings
from scene.base import Scene
from scene.camera import Intrinsics, Viewpoint, matrix_from_quat, mujoco_camera_pose


class SceneRenderer:
    """Renders RGB images of a scene from viewpoints (x, y, z, yaw_deg, pitch_deg).

    One OpenGL context and one compiled model are reused for every image. Use as a context manager
    or call ``close()``; the context is bound to the creating thread.
    """

    def __init__(self, scene: Scene, intrinsics: Intrinsics, render: RenderSettings):
        """Build the model and the off-screen context.

        Args:
            scene: the scene to draw (world metres).
            intrinsics: the camera (image size, field of view).
            render: the ``render`` settings (``backend``, lighting, shadows, ...).
        """
        if not isinstance(render, RenderSettings):
            raise TypeError(
                f"rendering takes RenderSettings (RenderSettings.from_config), not {type(render)}"
            )
        self.backend = select_backend(render.backend)
        # heavy (mujoco): imported on use
        import mujoco

        self._mujoco = mujoco
        self.intrinsics = intrinsics
        self.built: BuiltModel = build_model(scene, intrinsics, render)
        model = self.built.model
        self.model = model
        self.data = mujoco.MjData(model)
        mujoco.mj_forward(model, self.data)

        self._gl = gl_context_class(self.backend)(int(intrinsics.width), int(intrinsics.height))
        self._gl.make_current()
        self._check_texture_limit()
        self._con = mujoco.MjrContext(model, mujoco.mjtFontScale.mjFONTSCALE_100)
        mujoco.mjr_setBuffer(mujoco.mjtFramebuffer.mjFB_OFFSCREEN, self._con)

        self._scene = mujoco.MjvScene(model, maxgeom=model.ngeom + 16)
        flags = self._scene.flags
        flags[mujoco.mjtRndFlag.mjRND_SHADOW] = render.shadows.enabled
        flags[mujoco.mjtRndFlag.mjRND_SKYBOX] = True
        flags[mujoco.mjtRndFlag.mjRND_FOG] = False
        flags[mujoco.mjtRndFlag.mjRND_HAZE] = False
        flags[mujoco.mjtRndFlag.mjRND_REFLECTION] = False
        # Back faces stay visible: a scene with a few inverted faces must not show holes.
        flags[mujoco.mjtRndFlag.mjRND_CULL_FACE] = render.cull_backfaces
        self._option = mujoco.MjvOption()
        # Only the textured meshes: no light or camera glyphs, no frames, no convex hulls.
        self._option.flags[:] = 0
        self._option.flags[mujoco.mjtVisFlag.mjVIS_TEXTURE] = 1
        self._option.flags[mujoco.mjtVisFlag.mjVIS_STATIC] = 1
        self._camera = mujoco.MjvCamera()
        self._camera.type = mujoco.mjtCamera.mjCAMERA_FIXED
        self._camera.fixedcamid = self.built.camera_id
        self._rect = mujoco.MjrRect(0, 0, int(intrinsics.width), int(intrinsics.height))
        self._upside_down = np.empty((int(intrinsics.height), int(intrinsics.width), 3), np.uint8)

    def _check_texture_limit(self) -> None:
        # heavy (OpenGL): imported on use
        from OpenGL import GL

        limit = int(GL.glGetIntegerv(GL.GL_MAX_TEXTURE_SIZE))
        if self.built.max_texture_side > limit:
            raise ValueError(
                f"a texture of the scene is {self.built.max_texture_side} px on a side; the {self.backend} "
                f"OpenGL limit is {limit} px"
            )

    def render(self, viewpoint: Viewpoint | np.ndarray) -> np.ndarray:
        """RGB image (H, W, 3) uint8, row 0 at the top, of the scene seen from one viewpoint."""
        mujoco = self._mujoco
        row = viewpoint.as_array() if isinstance(viewpoint, Viewpoint) else np.asarray(viewpoint, float)
        if row.shape != (5,) or not np.all(np.isfinite(row)):
            raise ValueError(f"viewpoint must be 5 finite values (x, y, z, yaw, pitch), got {row.tolist()}")
        pos, quat = mujoco_camera_pose(row)
        cam = self.built.camera_id
        # The camera hangs from the static world body: its world pose is its model pose.
        self.model.cam_pos[cam] = pos
        self.model.cam_quat[cam] = quat
        self.data.cam_xpos[cam] = pos
        self.data.cam_xmat[cam] = matrix_from_quat(quat).ravel()
        mujoco.mjv_updateScene(
            self.model, self.data, self._option, None, self._camera, mujoco.mjtCatBit.mjCAT_ALL, self._scene
        )
        self._gl.make_current()
        mujoco.mjr_render(self._rect, self._scene, self._con)
        mujoco.mjr_readPixels(self._upside_down, None, self._rect, self._con)
        return self._upside_down[::-1].copy()

    def close(self) -> None:
        """Free the OpenGL resources (safe to call twice)."""
        if getattr(self, "_con", None) is not None:
            self._gl.make_current()
            self._con.free()
            self._con = None
        if getattr(self, "_gl", None) is not None:
            self._gl.free()
            self._gl = None

    def __enter__(self) -> SceneRenderer:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def __del__(self) -> None:
        try:
            self.close()
        except Exception:
            pass
