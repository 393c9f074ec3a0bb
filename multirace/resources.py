"""The data shipped inside the package: tracks, agents and league definitions.

The project keeps them in its top-level data folders (`tracks/`, `agents/`,
`league/`); the package reaches them as `multirace/data/<folder>` (links in
the source tree, copies in a wheel), found through `importlib.resources` the
same way from an editable install and from an installed wheel.
"""
from __future__ import annotations

from importlib.resources import files
from pathlib import Path


def data_dir(folder: str) -> Path:
    """The shipped data folder `folder` ("tracks", "agents" or "league")."""
    return Path(str(files("multirace").joinpath("data", folder)))


def tracks_dir() -> Path:
    """The bundled DeepRacer track files (.npy)."""
    return data_dir("tracks")


def agents_dir() -> Path:
    """The shipped agent files (.pt) and their action spaces."""
    return data_dir("agents")


def league_dir() -> Path:
    """The shipped league definitions (default.toml)."""
    return data_dir("league")


def list_tracks() -> list[str]:
    """Names of the bundled tracks."""
    return sorted(p.stem for p in tracks_dir().glob("*.npy"))


def list_agents() -> list[str]:
    """Names of the shipped agent files (`multirace race dagger_fast` races one by name)."""
    return sorted(p.stem for p in agents_dir().glob("*.pt"))
