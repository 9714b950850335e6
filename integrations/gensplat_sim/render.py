"""Offscreen MuJoCo rendering of RGB, metric depth and geom segmentation.

One OpenGL pass yields both the colour and the depth buffer (``mujoco.Renderer`` renders
twice for that). The depth buffer is linearised to metric camera-frame z; pixels on the far
plane (nothing hit) get 0, the library's "invalid" value.
"""

from __future__ import annotations

import atexit
import weakref

import mujoco
import numpy as np

_OPEN: weakref.WeakSet = weakref.WeakSet()


def _free(gl: mujoco.GLContext, con: mujoco.MjrContext) -> None:
    gl.make_current()
    con.free()
    gl.free()


def _close_all() -> None:
    for renderer in list(_OPEN):
        renderer.close()


class OffscreenRenderer:
    """Renders cameras of ``model`` at ``height x width``.

    Args:
        model: the compiled model (its ``vis.global_.offwidth/offheight`` bound the size).
        height, width: image size in pixels.
        shadows, reflections: MuJoCo's shadow and reflection passes (slow on a CPU).
    """

    def __init__(
        self, model: mujoco.MjModel, height: int, width: int, shadows: bool = False, reflections: bool = False
    ) -> None:
        if width > model.vis.global_.offwidth or height > model.vis.global_.offheight:
            raise ValueError(
                f"image {width}x{height} exceeds the offscreen buffer "
                f"{model.vis.global_.offwidth}x{model.vis.global_.offheight} (SceneConfig.max_image_size)"
            )
        self.model, self.height, self.width = model, height, width
        self._gl = mujoco.GLContext(width, height)
        self._gl.make_current()
        self._con = mujoco.MjrContext(model, mujoco.mjtFontScale.mjFONTSCALE_100)
        self._finalizer = weakref.finalize(self, _free, self._gl, self._con)
        self._finalizer.atexit = False
        if not _OPEN:  # (re-)register after the GL backend's own exit hook, so this one runs first
            atexit.unregister(_close_all)
            atexit.register(_close_all)
        _OPEN.add(self)
        mujoco.mjr_setBuffer(mujoco.mjtFramebuffer.mjFB_OFFSCREEN, self._con)
        self._con.readDepthMap = mujoco.mjtDepthMap.mjDEPTH_ZEROFAR
        self._scene = mujoco.MjvScene(model, maxgeom=2000)
        self._scene.flags[mujoco.mjtRndFlag.mjRND_SHADOW] = shadows
        self._scene.flags[mujoco.mjtRndFlag.mjRND_REFLECTION] = reflections
        self._option = mujoco.MjvOption()
        self._camera = mujoco.MjvCamera()
        self._camera.type = mujoco.mjtCamera.mjCAMERA_FIXED
        self._rect = mujoco.MjrRect(0, 0, width, height)
        self._rgb = np.empty((height, width, 3), np.uint8)
        self._zbuf = np.empty((height, width), np.float32)
        # Reversed-z perspective constants, in float32 like the GL projection matrix.
        near = np.float32(model.vis.map.znear * model.stat.extent)
        far = np.float32(model.vis.map.zfar * model.stat.extent)
        self._c = np.float64(np.float32(0.5) * (far + near) / (far - near) - np.float32(0.5))
        self._d = np.float64(far * near / (far - near))

    def _draw(self, data: mujoco.MjData, camera_id: int, segmentation: bool = False) -> None:
        self._gl.make_current()
        self._camera.fixedcamid = camera_id
        mujoco.mjv_updateScene(
            self.model, data, self._option, None, self._camera, mujoco.mjtCatBit.mjCAT_ALL, self._scene
        )
        self._scene.flags[mujoco.mjtRndFlag.mjRND_SEGMENT] = segmentation
        self._scene.flags[mujoco.mjtRndFlag.mjRND_IDCOLOR] = segmentation
        mujoco.mjr_render(self._rect, self._scene, self._con)

    def render(
        self, data: mujoco.MjData, camera_id: int, depth: bool = True
    ) -> tuple[np.ndarray, np.ndarray | None]:
        """RGB (H, W, 3) uint8 and metric depth (H, W) float32 (0 = nothing hit) of one camera."""
        self._draw(data, camera_id)
        mujoco.mjr_readPixels(self._rgb, self._zbuf if depth else None, self._rect, self._con)
        rgb = np.flipud(self._rgb).copy()
        if not depth:
            return rgb, None
        z = np.flipud(self._zbuf).astype(np.float64)
        metric = np.where(z > 0, self._d / np.maximum(z + self._c, 1e-12), 0.0)
        return rgb, metric.astype(np.float32)

    def segmentation(self, data: mujoco.MjData, camera_id: int) -> np.ndarray:
        """(H, W) int32 geom id seen at each pixel, -1 where no geom is hit."""
        self._draw(data, camera_id, segmentation=True)
        mujoco.mjr_readPixels(self._rgb, None, self._rect, self._con)
        seg = np.flipud(self._rgb).astype(np.int32)
        segid = seg[..., 0] + (seg[..., 1] << 8) + (seg[..., 2] << 16)  # 0 = background, else 1 + scene index
        lut = np.full(self._scene.ngeom + 1, -1, np.int32)
        for i in range(self._scene.ngeom):
            g = self._scene.geoms[i]
            if g.segid >= 0 and g.objtype == int(mujoco.mjtObj.mjOBJ_GEOM):
                lut[g.segid + 1] = g.objid
        return lut[np.clip(segid, 0, self._scene.ngeom)]

    def close(self) -> None:
        """Free the GL context (also done when garbage-collected or at exit)."""
        self._finalizer()
