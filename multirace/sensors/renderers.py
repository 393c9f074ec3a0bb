"""Choosing a camera renderer by name: the fast warp renderer or PyBullet's reference."""
from __future__ import annotations

from .camera import CameraSpec, Renderer
from .fast_renderer import FastRenderer
from .pybullet_renderer import PyBulletRenderer

RENDERERS = {"fast": FastRenderer, "pybullet": PyBulletRenderer}


def make_renderer(name: str, spec: CameraSpec, texture) -> Renderer:
    """Build the renderer called `name` ("fast" or "pybullet")."""
    if name not in RENDERERS:
        raise ValueError(f"renderer: unknown renderer {name!r}; choose 'fast' or 'pybullet'")
    return RENDERERS[name](spec, texture)
