"""Offscreen rendering through EGL: a reusable HeadlessRenderer and the one-call `render_image`.

    from client_gl.headless import render_image, HeadlessRenderer
    img = render_image(gaussians_or_scene_dir, camera)          # (H, W, 3) float32, linear, not clamped above

One GL context (and the renderer of the last loaded source) is kept per sort mode and reused across calls.
"""
from __future__ import annotations

import os
import threading

import numpy as np

from splatstream.camera import Camera
from splatstream.errors import SplatstreamError, UsageError
from splatstream.format.names import MANIFEST_NAME
from splatstream.gaussians import Gaussians

from .pool import ChunkPool
from .renderer import FrameStats, SplatRenderer
from .scene import DEFAULT_PRESET, SceneTiles, tiles_from_gaussians, tiles_from_scene


class GLUnavailableError(SplatstreamError):
    """No OpenGL context could be created (no EGL/GL libraries, no driver)."""


def create_context(require: int = 430):
    """A headless moderngl context: EGL with GL >= 4.3 if possible, else any GL >= 4.1 (CPU sort path)."""
    try:
        import moderngl
    except ImportError as exc:
        raise GLUnavailableError(f"moderngl is not installed ({exc}); pip install moderngl") from None
    errors = []
    attempts = [dict(backend="egl", require=require)]
    if require > 410:
        attempts.append(dict(backend="egl", require=410))
    attempts.append(dict(require=410))
    for kwargs in attempts:
        try:
            return moderngl.create_context(standalone=True, **kwargs)
        except Exception as exc:  # glcontext raises plain Exceptions with the loader's message
            errors.append(f"{kwargs.get('backend', 'default')}: {exc}")
    raise GLUnavailableError(
        "cannot create an OpenGL context for headless rendering (" + "; ".join(errors) + "). Install the EGL and "
        "Mesa libraries (Debian/Ubuntu: apt-get install libegl1 libgl1 libegl-mesa0 libgl1-mesa-dri libgbm1) or "
        "a GPU driver with EGL.")


class HeadlessRenderer:
    """One GL context; load Gaussians or an encoded scene, then render any number of cameras."""

    def __init__(self, sort: str = "auto", ctx=None, color_dtype: str = "f4", draw: str = "auto"):
        self.ctx = ctx or create_context()
        self.sort = sort
        self.color_dtype = color_dtype
        self.draw = draw
        self.pool: ChunkPool | None = None
        self.renderer: SplatRenderer | None = None
        self.scene: SceneTiles | None = None
        self.source_key = None

    # --- loading ---------------------------------------------------------------------------------------------
    def load_tiles(self, scene: SceneTiles, capacity: int | None = None) -> None:
        """Make a pool for the scene's formats and upload all its tiles."""
        self.unload()
        cap = max(capacity or 0, scene.splats, 1)
        self.pool = ChunkPool(self.ctx, scene.formats, scene.sh_degree, cap, codebook=scene.codebook)
        for tile_id, tile in scene.tiles.items():
            self.pool.join(tile_id, tile)
        self.renderer = SplatRenderer(self.ctx, self.pool, self.sort, self.color_dtype, self.draw)
        self.scene = scene

    def load_gaussians(self, g: Gaussians, preset: str = DEFAULT_PRESET, sh_degree: int | None = None) -> None:
        self.load_tiles(tiles_from_gaussians(g, preset, sh_degree))

    def load_scene(self, scene_dir: str | os.PathLike, sh_degree: int | None = None) -> None:
        self.load_tiles(tiles_from_scene(scene_dir, sh_degree))

    def unload(self) -> None:
        if self.renderer is not None:
            self.renderer.release()
        if self.pool is not None:
            self.pool.release()
        self.pool = self.renderer = self.scene = None
        self.source_key = None

    # --- rendering -------------------------------------------------------------------------------------------
    def render(self, camera: Camera, sh_degree: int | None = None, background=(0.0, 0.0, 0.0),
               timing: bool = False) -> np.ndarray:
        """(H, W, 3) float32 linear colour (composited over `background`), row 0 at the top."""
        self.render_frame(camera, sh_degree, background, timing)
        if self.renderer.check_bins():  # compute draw: the entry buffer overflowed and grew; read back anyway
            self.render_frame(camera, sh_degree, background, timing)
        return self.renderer.read_image()[..., :3]

    def render_frame(self, camera: Camera, sh_degree: int | None = None, background=(0.0, 0.0, 0.0),
                     timing: bool = False) -> FrameStats:
        if self.renderer is None:
            raise UsageError("nothing loaded: call load_gaussians() or load_scene() first")
        return self.renderer.render(camera, sh_degree, background, timing=timing)

    @property
    def sort_mode(self) -> str | None:
        return self.renderer.sort_mode if self.renderer else None

    def close(self) -> None:
        self.unload()
        self.ctx.release()


_shared: dict[str, HeadlessRenderer] = {}
_lock = threading.Lock()


def _source_key(source) -> tuple:
    if isinstance(source, Gaussians):
        return ("g", id(source), len(source))
    path = os.path.realpath(os.fspath(source))
    manifest = os.path.join(path, MANIFEST_NAME)
    return ("dir", path, os.path.getmtime(manifest) if os.path.exists(manifest) else None)


def get_renderer(sort: str = "auto") -> HeadlessRenderer:
    with _lock:
        r = _shared.get(sort)
        if r is None:
            r = _shared[sort] = HeadlessRenderer(sort=sort)
        return r


def render_image(source: Gaussians | str | os.PathLike, camera: Camera, sh_degree: int | None = None,
                 background=(0.0, 0.0, 0.0), sort: str = "auto", preset: str = DEFAULT_PRESET) -> np.ndarray:
    """Render Gaussians (encoded in memory at `preset`, very-high by default) or an encoded scene directory.

    Returns (H, W, 3) float32. The context and the loaded source are kept for the next call (same source object
    or directory: no re-upload).
    """
    r = get_renderer(sort)
    key = _source_key(source) + ((preset,) if isinstance(source, Gaussians) else ())
    if r.source_key != key:
        if isinstance(source, Gaussians):
            r.load_gaussians(source, preset)
            r._source_ref = source  # keep the object alive so its id stays unique while cached
        else:
            r.load_scene(source)
        r.source_key = key
    return r.render(camera, sh_degree, background)
