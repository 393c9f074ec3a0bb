"""The data shipped inside the package: tracks, agents and league definitions.

The project keeps them in its top-level data folders (`tracks/`, `agents/`,
`league/`); the package reaches them as `multirace/data/<folder>` (links in
the source tree, copies in a wheel), found through `importlib.resources` the
same way from an editable install and from an installed wheel.
"""
from __future__ import annotations

import re
from importlib.resources import files
from pathlib import Path

_GLANCE_ROW = re.compile(r"^\| `(?P<name>[^`]+)` \| (?P<held_out>[^|]+) \| (?P<traffic>[^|]+) \|$")


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


def shipped_figures() -> dict[str, dict]:
    """Each shipped agent's headline figures, {name: {"held_out", "traffic"}}, from the "At a glance" table of
    the shipped agents/README.md (the measurements live there, with how they were made)."""
    readme = agents_dir() / "README.md"
    text = readme.read_text() if readme.exists() else ""
    glance = text.partition("## At a glance")[2].partition("\n## ")[0]
    return {m["name"]: {"held_out": m["held_out"].strip(), "traffic": m["traffic"].strip()}
            for m in map(_GLANCE_ROW.match, glance.splitlines()) if m}


def resolve_agent_path(spec) -> Path:
    """The agent file `spec` names: a path, or else the name of an agent shipped with multirace (`racer`).

    Every command and function that takes an agent file goes through here, so a shipped agent's name
    works wherever a path does; a path that exists (a file of that name here) comes first."""
    path = Path(spec)
    shipped = agents_dir() / f"{spec}.pt"
    if not path.is_file() and path.name == str(spec) and shipped.exists():  # a bare name: a folder of that
        return shipped                                                       # name does not shadow the agent
    return path


def agent_argument(spec: str) -> str:
    """`resolve_agent_path` as an argparse `type`: every command-line argument that takes an agent file. A name
    that is neither a file nor a shipped agent is refused as the arguments are read, before any work."""
    import argparse

    path = resolve_agent_path(spec)
    if not path.exists():
        raise argparse.ArgumentTypeError(f"{spec}: no such agent file, and no shipped agent of that name "
                                         f"(`multirace agent list` shows them)")
    return str(path)

