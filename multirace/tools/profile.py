"""`multirace bench --profile`: where the time of an env step and of its floor goes, and the renderer alone.

The stages of `RaceEnv.step`: commands (the actions read as commands, with
DeepRacer's noise), dynamics (the car model: pushes, tyre kernel, free
moves, the broad phase), contacts (PyBullet: syncing bodies, stepping,
contact points, reading poses and pushes), rules (track measurement,
contacts and the race rules, publishing the race state), params (the reward
params and infos), reward (the reward function) and render (the
observations); beside them the bench's floor for the same workload
(`bench._floor_stepper`: the env's physics alone and a texture warp per
camera) split into its physics and its warps (the wrappers slow the
profiled step by a few us, so the step's ratio to its floor is read from
`multirace bench`, not from here). Each is timed by wrapping the env's, its race core's and the
world's own methods on one instance with `time.perf_counter`, so the code of
an unprofiled env is untouched; what no stage covers (the step's own glue:
its dicts, the race's end) is "other".
"""
from __future__ import annotations

import time

import numpy as np

from ..sensors.camera import CameraSpec, camera_poses
from ..sensors.fast_renderer import FastRenderer

STAGES = ("commands", "dynamics", "contacts", "rules", "params", "reward", "render", "other")
# the methods timed as each stage: (object: "env", "core", "world" or "reward"; method names)
_TIMED = {
    "commands": ("env", ("_commands_for",)),
    "dynamics": ("world", ("_pushes", "_command_dynamic", "_command_kinematic", "_may_touch", "_move_freely")),
    "rules": ("core", ("_measure_all", "_apply_contacts", "apply_rules", "publish")),
    "params": ("env", ("_reward_params", "_info")),
    "reward": ("reward", ("rewards",)),
    "render": ("env", ("_observe",)),
}


def _timed(method, totals: dict, stage: str):
    def wrapper(*args, **kwargs):
        start = time.perf_counter()
        try:
            return method(*args, **kwargs)
        finally:
            totals[stage] += time.perf_counter() - start
    return wrapper


def profile_step(step, env, steps: int) -> dict:
    """Microseconds per env step of each stage, over `steps` calls of `step` (which steps `env`)."""
    totals = dict.fromkeys(STAGES + ("world", "total"), 0.0)
    owners = {"env": env, "core": env.core, "world": env.world, "reward": env.reward_function}
    for stage, (owner, names) in _TIMED.items():
        for name in names:
            setattr(owners[owner], name, _timed(getattr(owners[owner], name), totals, stage))
    env.world.step = _timed(env.world.step, totals, "world")
    try:
        _run(step, steps, totals)
    finally:
        for owner, names in _TIMED.values():
            for name in names:
                delattr(owners[owner], name)  # the class's own methods again
        del env.world.step
    totals["contacts"] = totals.pop("world") - totals["dynamics"]
    covered = sum(totals[stage] for stage in STAGES if stage != "other")
    totals["other"] = totals["total"] - covered
    return _per_step(totals, steps)


def profile_floor(step, world, steps: int) -> dict:
    """Microseconds per step of the bench's floor (`bench._floor_stepper`'s `step`, which steps `world`): its
    physics (`World.step`: the tyre model and PyBullet) and the rest (one texture warp per camera, the replay)."""
    totals = {"physics": 0.0, "total": 0.0}
    world.step = _timed(world.step, totals, "physics")
    try:
        _run(step, steps, totals)
    finally:
        del world.step  # the class's own method again
    totals["warps"] = totals["total"] - totals["physics"]
    return _per_step(totals, steps)


def _run(step, steps: int, totals: dict) -> None:
    """Call `step` `steps` times, adding the wall time of the calls to totals["total"]."""
    for _ in range(steps):
        start = time.perf_counter()
        step()
        totals["total"] += time.perf_counter() - start


def _per_step(totals: dict, steps: int) -> dict:
    """Seconds in all steps as microseconds per step, one decimal."""
    return {part: round(1e6 * seconds / steps, 1) for part, seconds in totals.items()}


def renderer_step(env):
    """A step function that draws one frame with the fast renderer alone: a 120x160 grey camera on `env`'s
    track and world, where `env`'s first car is now (the same view at every call)."""
    spec = CameraSpec(height=120, width=160, grayscale=True)
    renderer, world = FastRenderer(spec, env.texture), env.world
    eyes, rotations = camera_poses(spec, world.poses[:1].copy())
    cars = np.zeros(1, np.int64)

    def step():
        renderer.render_many(world, cars, eyes, rotations)

    step()  # compile / warm up
    return step


def renderer_frames_per_s(env, frames: int = 400, windows: int = 5) -> float:
    """Frames per second of the fast renderer alone (`renderer_step`), the best of `windows` timings of
    `frames` frames."""
    step, best = renderer_step(env), 0.0
    for _ in range(windows):
        start = time.perf_counter()
        for _ in range(frames):
            step()
        best = max(best, frames / (time.perf_counter() - start))
    return best


def format_profile(profile: dict) -> list[tuple[str, str]]:
    """(stage, value) rows for printing."""
    split = profile["us_per_step"]
    rows = [(stage, f"{split[stage]:.1f} us ({100 * split[stage] / split['total']:.0f} %)") for stage in STAGES]
    floor = profile["floor_us_per_step"]
    rows += [("whole step", f"{split['total']:.1f} us"),
             ("floor: physics (tyre model, PyBullet)", f"{floor['physics']:.1f} us"),
             ("floor: camera warps (and its replay's glue)", f"{floor['warps']:.1f} us"),
             ("steps that ran PyBullet", f"{100 * profile['pybullet_step_share']:.0f} %"),
             ("renderer alone, 120x160 grey (frames/s)", f"{profile['renderer_frames_per_s']:,.0f}")]
    return rows
