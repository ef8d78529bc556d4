"""Which renderer a command uses: the GL client when it can open a context here, else the numpy reference.

This is the wiring layer: the core (splatstream.evaluate) is handed a renderer and never imports client_gl.
"""
from __future__ import annotations

import numpy as np

from splatstream.errors import UsageError
from splatstream.evaluate import EvalRenderer, reference_renderer

RENDERER_CHOICES = ("auto", "gl", "ref")


GL_EXTRA_HINT = "pip install 'splatstream[view]'"


def gl_client():
    """client_gl.headless, or a UsageError saying how to install the GL client."""
    try:
        from client_gl import headless
    except ImportError as exc:
        raise UsageError(f"the GL client is not installed ({exc.name or exc}): {GL_EXTRA_HINT}") from None
    return headless


def gl_renderer() -> EvalRenderer | None:
    """The GL client's headless renderer, if moderngl is installed and a context opens here."""
    try:
        from client_gl import headless
    except ImportError:  # the GL extra is not installed: the reference renderer does the job
        return None
    try:
        headless.get_renderer()  # opens the shared context now, so a machine without GL falls back cleanly
    except headless.GLUnavailableError:
        return None
    return EvalRenderer(lambda src, cam: np.asarray(headless.render_image(src, cam), dtype=np.float32),
                        "gl (client_gl.headless.render_image)", "gl", draws_scenes=True)


def pick_renderer(kind: str = "auto") -> EvalRenderer:
    if kind not in RENDERER_CHOICES:
        raise UsageError(f"unknown renderer {kind!r} (choose auto, gl or ref)")
    if kind in ("auto", "gl"):
        found = gl_renderer()
        if found is not None:
            return found
        if kind == "gl":
            raise UsageError("the GL renderer (client_gl.headless) cannot render here; use --renderer ref")
    return reference_renderer()
