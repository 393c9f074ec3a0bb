"""The league worker: a subprocess that validates agent files and runs matches, one JSON line per request.

Agent files are untrusted, so the league parent never loads one; `python -m multirace.league worker`
serves requests on stdin and answers on stdout.
"""
from __future__ import annotations

import json
import os
import sys
import time
from pathlib import Path

from .config import LeagueError
from .store import submission_problem


def _worker_command() -> list[str]:
    return [sys.executable, "-m", "multirace.league", "worker"]


def _worker_env() -> dict:
    env = dict(os.environ)
    env.setdefault("OMP_NUM_THREADS", "1")
    env.setdefault("MKL_NUM_THREADS", "1")
    package_root = str(Path(__file__).resolve().parents[2])  # the folder that holds `multirace`
    env["PYTHONPATH"] = package_root + (os.pathsep + env["PYTHONPATH"] if env.get("PYTHONPATH") else "")
    return env


def _entrant_controller(entrant: dict, folder: Path):
    """The controller of one scheduled entrant. An agent file that cannot be loaded for any reason forfeits
    its races (with the reason) rather than failing the match: one entrant never voids its opponents' heats.
    A stored file that is not the one submitted (its sha256 differs) fails the match, naming the entrant:
    that is the league's storage at fault, not the entrant."""
    from ..racing.entrant import Controller, Forfeit
    from ..racing.runner import make_controller

    if entrant["spec"].startswith("bot:"):
        return make_controller(entrant["spec"])
    problem = submission_problem(folder, entrant["name"], entrant["sha256"], entrant["spec"])
    if problem:
        raise LeagueError(problem)
    try:
        controller = make_controller(str(folder / entrant["spec"]), step_budget=entrant["step_budget"])
    except FileNotFoundError:  # the league lost the file: the match fails with the reason, nobody forfeits
        raise
    except Exception as exc:  # noqa: BLE001 - whatever a stranger's file makes the loader raise
        reason = f"agent file cannot be loaded ({type(exc).__name__}: {str(exc)[:200]})"
    else:
        if controller.file_sha256 != entrant["sha256"]:  # the bytes loaded, if the file changed since
            raise LeagueError(submission_problem(folder, entrant["name"], entrant["sha256"], entrant["spec"])
                              or f"entrant {entrant['name']!r}: its stored file {entrant['spec']} changed while "
                                 "it was loaded")
        return controller

    class Unloadable(Controller):
        file_sha256 = entrant.get("sha256")

        def act(self, observation, info):
            raise Forfeit(reason)

    return Unloadable()


def run_match(spec: dict, folder, replay: str | None, image_every: int = 0) -> dict:
    """Run one scheduled match (in a worker process); returns the race result record."""
    from ..racing.runner import RaceConfig, run_race

    folder = Path(folder)
    controllers = []
    for e in spec["entrants"]:
        controller = _entrant_controller(e, folder)
        controller.name = e["name"]
        controllers.append(controller)
    config = RaceConfig(track=spec["track"], reverse=spec["reverse"], race=spec["race"], laps=spec["laps"],
                        seed=spec["seed"], max_steps=spec["max_steps"])
    recorders = []
    if replay:
        from ..recording.replay import ReplayRecorder

        recorders.append(ReplayRecorder(replay, image_every=image_every))
    return run_race(controllers, config, recorders=recorders)


def _handle(request: dict) -> dict:
    if request.get("op") == "validate":
        from ..racing.agentfile import AgentFileError, load_agent

        try:
            agent = load_agent(request["path"], step_budget=request["step_budget"])
        except (AgentFileError, FileNotFoundError) as exc:
            return {"ok": False, "error": str(exc)}
        return {"ok": True, "name": agent.name, "sha256": agent.sha256, "metadata": agent.metadata}
    if request.get("op") == "match":
        spec = request["spec"]
        start = time.perf_counter()  # the replay is written atomically: complete, or not at all
        result = run_match(spec, request["folder"], request.get("replay"), request.get("image_every", 0))
        return {"ok": True, "result": result, "wall_seconds": time.perf_counter() - start}
    return {"ok": False, "error": f"unknown request {request.get('op')!r}"}


def worker_main() -> int:
    """A league worker: reads one JSON request per line on stdin, answers one JSON line each on stdout.

    The protocol channel is the original stdout; anything the race code prints goes to stderr.
    """
    channel = os.fdopen(os.dup(1), "w", buffering=1)
    os.dup2(2, 1)
    sys.stdout = sys.stderr
    if "--serve" in sys.argv:  # a long-lived match worker: import the heavy parts, then say so
        from ..racing import agentfile, runner  # noqa: F401

        channel.write(json.dumps({"ready": True}) + "\n")
        channel.flush()
    for line in sys.stdin:
        if not line.strip():
            continue
        request = json.loads(line)
        try:
            answer = _handle(request)
        except Exception as exc:  # a bug or environment problem: report it, the parent retries
            import traceback

            answer = {"ok": False, "error": f"{type(exc).__name__}: {exc}",
                      "traceback": traceback.format_exc()[-2000:]}
        channel.write(json.dumps(answer, default=float) + "\n")
        channel.flush()
    return 0
