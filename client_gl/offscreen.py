"""Offscreen rendering through EGL: a reusable HeadlessRenderer and the one-call `render_image`.

    from client_gl.offscreen import render_image, HeadlessRenderer
    img = render_image(gaussians_or_scene_dir, camera)          # (H, W, 3) float32, linear, not clamped above
    r = HeadlessRenderer(RenderOptions(sort="cpu"))                # client_gl.gpu.renderer.RenderOptions
    r.load_scene(scene_dir)
    img = r.render(camera)

One GL context (shared_context) and one renderer per sort mode (with the last source it loaded) are kept and reused
across calls. This is a renderer of still images (`render`, `eval`); streaming a scene without a window
(`view --headless`) is client_gl.view_headless, which opens its context here.
"""
from __future__ import annotations

import os
import threading
from dataclasses import replace

import numpy as np

from splatstream.camera import Camera
from splatstream.errors import SplatstreamError, UsageError
from splatstream.format.names import MANIFEST_NAME
from splatstream.gaussians import Gaussians

from .gpu.pool import ChunkPool
from .gpu.renderer import FrameStats, RenderOptions, SplatRenderer, resolve_sort
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

    def __init__(self, options: RenderOptions | None = None, ctx=None):
        self.ctx = ctx or create_context()
        self.options = options or RenderOptions()
        # The CPU-sort path culls on the host: only then do the tiles carry (and the pool keep) a host mirror.
        self.needs_host_mirror = resolve_sort(self.ctx, self.options) == "cpu"
        self.pool: ChunkPool | None = None
        self.renderer: SplatRenderer | None = None
        self.scene: SceneTiles | None = None
        self._source: tuple[tuple, object] | None = None  # (key, source object) of load_cached's last source

    # --- loading ---------------------------------------------------------------------------------------------
    def load_tiles(self, scene: SceneTiles) -> None:
        """Make a pool of exactly the scene's slots and upload all its tiles (with their SH bands)."""
        self.unload()
        self.pool = ChunkPool(self.ctx, scene.formats, scene.sh_degree, max(1, scene.slots),
                              codebook=scene.codebook_layout, host_mirror=self.needs_host_mirror,
                              prime=self.options.atlas_prime)
        for name, plane in sorted((scene.codebook or {}).items()):
            self.pool.set_codebook_band(int(name[2:]), plane)
        for tile_id, tile in scene.tiles.items():
            self.pool.join(tile_id, tile)
        # Every image read back is a finished one (one-shot renders, the render benchmarks): the compute draw's
        # programs before the first frame, not after it (RenderOptions.defer_compute and cpu_first are the
        # streaming client's).
        self.renderer = SplatRenderer(self.ctx, self.pool, replace(self.options, defer_compute=False, cpu_first=False))
        self.scene = scene

    def load_gaussians(self, g: Gaussians, preset: str = DEFAULT_PRESET, sh_degree: int | None = None) -> None:
        self.load_tiles(tiles_from_gaussians(g, preset, sh_degree, with_mirror=self.needs_host_mirror))

    def load_scene(self, scene_dir: str | os.PathLike, sh_degree: int | None = None) -> None:
        self.load_tiles(tiles_from_scene(scene_dir, sh_degree, with_mirror=self.needs_host_mirror))

    def load_cached(self, source: Gaussians | str | os.PathLike, preset: str = DEFAULT_PRESET) -> None:
        """Load Gaussians (encoded at `preset`) or a scene directory unless it is the one loaded last (the same
        object, or the same directory with an unchanged manifest)."""
        key = _source_key(source) + ((preset,) if isinstance(source, Gaussians) else ())
        if self._source is not None and self._source[0] == key:
            return
        if isinstance(source, Gaussians):
            self.load_gaussians(source, preset)
        else:
            self.load_scene(source)
        self._source = (key, source)  # the object stays referenced, so its id stays unique while cached

    def unload(self) -> None:
        if self.renderer is not None:
            self.renderer.release()
        if self.pool is not None:
            self.pool.release()
        self.pool = self.renderer = self.scene = None
        self._source = None

    # --- rendering -------------------------------------------------------------------------------------------
    def render(self, camera: Camera, sh_degree: int | None = None, background=(0.0, 0.0, 0.0),
               timing: bool = False) -> np.ndarray:
        """(H, W, 3) float32 linear colour (composited over `background`), row 0 at the top."""
        self.render_frame(camera, sh_degree, background, timing)
        if self.renderer.check_bins(exact=True):  # compute draw: the entry buffer overflowed and grew
            self.render_frame(camera, sh_degree, background, timing)
        return self.renderer.read_image()[..., :3]

    def render_frame(self, camera: Camera, sh_degree: int | None = None, background=(0.0, 0.0, 0.0),
                     timing: bool = False) -> FrameStats:
        if self.renderer is None:
            raise UsageError("nothing loaded: call load_gaussians() or load_scene() first")
        return self.renderer.render(camera, sh_degree=sh_degree, background=background, timing=timing)

    @property
    def sort_mode(self) -> str | None:
        return self.renderer.sort_mode if self.renderer else None

    def close(self) -> None:
        self.unload()
        self.ctx.release()


_shared: dict[str, HeadlessRenderer] = {}
_shared_context = None
_lock = threading.Lock()


def shared_context():
    """The process's shared headless GL context (created on first use; GLUnavailableError where none opens).

    One context for every shared renderer and for tests: moderngl and the raw GL calls act on the context current
    on the thread, so objects of several contexts used in turn would end up in the wrong one."""
    global _shared_context
    with _lock:
        if _shared_context is None:
            _shared_context = create_context()
        return _shared_context


def _source_key(source) -> tuple:
    if isinstance(source, Gaussians):
        return ("g", id(source), len(source))
    path = os.path.realpath(os.fspath(source))
    manifest = os.path.join(path, MANIFEST_NAME)
    return ("dir", path, os.path.getmtime(manifest) if os.path.exists(manifest) else None)


def get_renderer(sort: str = "auto") -> HeadlessRenderer:
    """The shared renderer of a sort mode, on the shared context."""
    ctx = shared_context()
    with _lock:
        r = _shared.get(sort)
        if r is None:
            r = _shared[sort] = HeadlessRenderer(RenderOptions(sort=sort), ctx=ctx)
        return r


def render_image(source: Gaussians | str | os.PathLike, camera: Camera, sh_degree: int | None = None,
                 background=(0.0, 0.0, 0.0), sort: str = "auto", preset: str = DEFAULT_PRESET) -> np.ndarray:
    """Render Gaussians (encoded in memory at `preset`, very-high by default) or an encoded scene directory.

    Returns (H, W, 3) float32. The context and the loaded source are kept for the next call (same source object
    or directory: no re-upload).
    """
    r = get_renderer(sort)
    r.load_cached(source, preset)
    return r.render(camera, sh_degree, background)
