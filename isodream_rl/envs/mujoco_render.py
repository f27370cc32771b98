"""Offscreen MuJoCo rendering that does not depend on import order and survives ``fork``.

``mujoco.Renderer`` takes its OpenGL backend from ``mujoco.GLContext``, which mujoco fixes from ``MUJOCO_GL`` when
it is first imported. ``import torchrl.envs`` imports mujoco, so a program that imports torchrl before setting
``MUJOCO_GL`` gets GLFW, which needs a display.
:class:`OffscreenRenderer` picks a headless backend itself when it renders: the one ``MUJOCO_GL`` names now if it is
``"egl"``, ``"osmesa"`` or ``"glfw"``, else EGL, then OSMesa if EGL cannot make a context.

The GL context is made at the first render, in the process that renders, never at construction: an env can be
built in one process and used in a forked worker (TorchRL's ``ParallelEnv`` builds one in the parent to read its
specs). A context inherited through ``fork`` is dropped and a new one made in the child.
"""

from __future__ import annotations

import atexit
import importlib
import os
import weakref
from typing import Any

import mujoco
import numpy as np

from isodream_rl.process_settings import single_threaded_llvmpipe

__all__ = ["OffscreenRenderer", "create_gl_context"]

_HEADLESS_BACKENDS = ("egl", "osmesa")


def create_gl_context(width: int, height: int) -> tuple[str, Any]:
    """Makes an OpenGL context for MuJoCo with an explicitly chosen backend.

    Args:
        width (int): largest framebuffer width the context must support, in pixels.
        height (int): largest framebuffer height, in pixels.

    Returns:
        tuple: the backend name (``"egl"``, ``"osmesa"`` or ``"glfw"``) and its ``GLContext`` (not yet current).

    Raises:
        RuntimeError: when no backend can make a context; the message lists each backend's error.
    """
    single_threaded_llvmpipe()
    requested = os.environ.get("MUJOCO_GL", "").strip().lower()
    if requested in (*_HEADLESS_BACKENDS, "glfw"):
        order = [requested, *(b for b in _HEADLESS_BACKENDS if b != requested)]
    else:
        order = list(_HEADLESS_BACKENDS)
    errors = []
    for backend in order:
        try:
            context_class = importlib.import_module(f"mujoco.{backend}").GLContext
            return backend, context_class(width, height)
        except Exception as err:  # a missing library, no device, a PyOpenGL platform clash: try the next one
            errors.append(f"{backend}: {type(err).__name__}: {err}")
    raise RuntimeError(
        "Could not create an OpenGL context for MuJoCo rendering. Tried "
        + "; ".join(errors)
        + ". Headless rendering needs EGL (libegl1 and Mesa, in most base images) or OSMesa "
        "(apt-get install libosmesa6)."
    )


class _GLResources:
    """A GL context and the MuJoCo render context living in it, owned by the process that made them."""

    def __init__(self, model: mujoco.MjModel, width: int, height: int) -> None:
        self.pid = os.getpid()
        self.backend, self.gl = create_gl_context(width, height)
        self.gl.make_current()
        self.mjr = mujoco.MjrContext(model, mujoco.mjtFontScale.mjFONTSCALE_50)
        mujoco.mjr_setBuffer(mujoco.mjtFramebuffer.mjFB_OFFSCREEN, self.mjr)

    def free(self) -> None:
        if self.pid != os.getpid():
            return  # the parent's objects, copied by fork: the child must not touch the parent's GL state
        if self.mjr is not None:
            self.gl.make_current()
            self.mjr.free()
            self.mjr = None
        if self.gl is not None:
            self.gl.free()
            self.gl = None


class OffscreenRenderer:
    """Renders RGB frames of a MuJoCo model from a fixed camera, headless.

    Args:
        model (mujoco.MjModel): the model; its ``vis.global_.offwidth``/``offheight`` must be at least the image
            size.
        width (int): image width in pixels.
        height (int): image height in pixels.
        max_geom (int, optional): capacity of the abstract scene. Defaults to 1000.

    Examples:
        >>> model = mujoco.MjModel.from_xml_string(
        ...     '<mujoco><worldbody><camera name="c" pos="0 0 1"/><geom size="1 1 .1" type="plane"/>'
        ...     "</worldbody></mujoco>"
        ... )
        >>> renderer = OffscreenRenderer(model, width=64, height=64)  # no GL context yet
        >>> frame = renderer.render(mujoco.MjData(model), camera_id=0)  # made here
        >>> frame.shape, frame.dtype
        ((64, 64, 3), dtype('uint8'))
        >>> renderer.close()
    """

    def __init__(self, model: mujoco.MjModel, *, width: int, height: int, max_geom: int = 1000) -> None:
        if width > model.vis.global_.offwidth or height > model.vis.global_.offheight:
            raise ValueError(
                f"a {width}x{height} image needs the model's offscreen buffer to be at least that large, got "
                f"offwidth={model.vis.global_.offwidth}, offheight={model.vis.global_.offheight}"
            )
        self._model = model
        self._width, self._height = width, height
        self._scene = mujoco.MjvScene(model, maxgeom=max_geom)
        self._camera = mujoco.MjvCamera()
        self._camera.type = mujoco.mjtCamera.mjCAMERA_FIXED
        self._default_option = mujoco.MjvOption()
        self._rect = mujoco.MjrRect(0, 0, width, height)
        self._pixels = np.empty((height, width, 3), dtype=np.uint8)
        self._gl: _GLResources | None = None
        self._release: weakref.finalize | None = None
        self._closed = False

    @property
    def backend(self) -> str | None:
        """The OpenGL backend in use in this process (``"egl"``, ``"osmesa"``, ``"glfw"``), ``None`` before the
        first render."""
        gl = self._gl
        return gl.backend if gl is not None and gl.pid == os.getpid() else None

    def render(
        self, data: mujoco.MjData, *, camera_id: int, scene_option: mujoco.MjvOption | None = None
    ) -> np.ndarray:
        """Draws ``data`` as seen from the model's camera ``camera_id``.

        Args:
            data (mujoco.MjData): state to draw; its kinematics (``mj_kinematics``, ``mj_camlight``) must be current.
            camera_id (int): index of a camera of the model.
            scene_option (mujoco.MjvOption, optional): visibility options (geom groups, ...).

        Returns:
            np.ndarray: a new uint8 RGB image of shape [height, width, 3], top row first.
        """
        gl = self._update_scene("render", data, camera_id, scene_option)
        mujoco.mjr_render(self._rect, self._scene, gl.mjr)
        mujoco.mjr_readPixels(self._pixels, None, self._rect, gl.mjr)
        return np.flipud(self._pixels).copy()  # OpenGL's first row is the bottom one

    def _update_scene(
        self, caller: str, data: mujoco.MjData, camera_id: int, scene_option: mujoco.MjvOption | None
    ) -> _GLResources:
        """Makes this process's GL context current and fills the abstract scene of ``data`` from the camera."""
        if self._closed:
            raise RuntimeError(f"{caller}() called after close()")
        gl = self._context()
        gl.gl.make_current()  # another renderer in this thread (dm_control) may have made its own current
        self._camera.fixedcamid = camera_id
        mujoco.mjv_updateScene(
            self._model,
            data,
            scene_option or self._default_option,
            None,
            self._camera,
            mujoco.mjtCatBit.mjCAT_ALL,
            self._scene,
        )
        return gl

    def render_geom_ids(
        self, data: mujoco.MjData, *, camera_id: int, scene_option: mujoco.MjvOption | None = None
    ) -> np.ndarray:
        """The model geom drawn at each pixel of :meth:`render`'s image of the same state (MuJoCo's segmentation
        pass: flat id colours, no lighting). Without multisampling both passes rasterise the same triangles,
        so the two images agree pixel for pixel.

        Args:
            data (mujoco.MjData): state to draw, as for :meth:`render`.
            camera_id (int): index of a camera of the model.
            scene_option (mujoco.MjvOption, optional): visibility options (geom groups, ...).

        Returns:
            np.ndarray: int32 ``[height, width]``, the geom id at each pixel, ``-1`` where no geom is drawn.
        """
        gl = self._update_scene("render_geom_ids", data, camera_id, scene_option)
        scene = self._scene
        flags = scene.flags.copy()
        scene.flags[mujoco.mjtRndFlag.mjRND_SEGMENT] = True
        scene.flags[mujoco.mjtRndFlag.mjRND_IDCOLOR] = True
        try:
            mujoco.mjr_render(self._rect, scene, gl.mjr)
            mujoco.mjr_readPixels(self._pixels, None, self._rect, gl.mjr)
        finally:
            np.copyto(scene.flags, flags)
        rgb = np.flipud(self._pixels).astype(np.int64)
        segment = rgb[..., 0] + (rgb[..., 1] << 8) + (rgb[..., 2] << 16)  # segid + 1, 0 where nothing
        lookup = np.full(scene.ngeom + 2, -1, dtype=np.int32)
        for geom in scene.geoms[: scene.ngeom]:
            if geom.segid >= 0 and geom.objtype == mujoco.mjtObj.mjOBJ_GEOM:
                lookup[geom.segid + 1] = geom.objid
        return lookup[np.minimum(segment, scene.ngeom + 1)]

    def close(self) -> None:
        """Releases the GL resources; the renderer cannot render afterwards."""
        self._closed = True
        if self._release is not None:
            atexit.unregister(self._release)
            self._release()

    def _context(self) -> _GLResources:
        if self._gl is None or self._gl.pid != os.getpid():
            self._gl = _GLResources(self._model, self._width, self._height)
            self._release = weakref.finalize(self, self._gl.free)  # at garbage collection
            # ... or at exit, before the EGL display is terminated: mujoco.egl registers that exit hook when it
            # makes its first context, and exit hooks run last registered first.
            atexit.register(self._release)
        return self._gl
