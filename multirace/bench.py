"""`multirace bench`: throughput figures and ratios, all from one run on this machine.

Measures agent-steps per second (one car's observation, reward and info per
15 Hz step) of the full env (cameras, physics with collisions, obstacles,
random actions, full reward params and infos) for 1, 2, 4 and 8 cars with the
fast renderer and with the PyBullet renderer; the floor (the physics steps
alone plus one bare texture warp per camera); the speed-up of two worker
processes over one; peak memory; and the cost of recording a replay.
"""
from __future__ import annotations

import functools
import resource
import time

import cv2
import numpy as np

from .camera import camera_pose
from .env import RaceEnv

CAR_COUNTS = (1, 2, 4, 8)
WINDOWS = 5  # each figure is the best of this many equal time windows
OBSTACLES = 3


def _best_rate(step, agents_per_step: int, seconds: float, windows: int = WINDOWS) -> float:
    """Agent-steps per second of `step()`: the best of several short windows.

    Other processes on a 2-core machine slow some windows down; the best window
    is the closest to what the code itself costs.
    """
    best = 0.0
    for _ in range(windows):
        steps, start = 0, time.perf_counter()
        while time.perf_counter() - start < seconds / windows:
            step()
            steps += 1
        best = max(best, agents_per_step * steps / (time.perf_counter() - start))
    return best


def _bench_env(num_cars: int, renderer: str, seconds: float, seed: int = 0) -> float:
    """Agent-steps per second of the env stepped with random actions (resetting when done)."""
    env = RaceEnv(num_cars=num_cars, obstacles=OBSTACLES, renderer=renderer, max_steps=2000)
    rng = np.random.default_rng(seed)
    env.reset(seed=seed)
    n_actions = env.actions.space.n

    def step():
        if not env.agents:
            env.reset()
        env.step({a: int(rng.integers(n_actions)) for a in env.agents})

    step()  # warm-up
    rate = _best_rate(step, num_cars, seconds)
    env.close()
    return rate


def _bench_floor(num_cars: int, seconds: float, seed: int = 0) -> float:
    """Agent-steps per second of the bare minimum: physics steps plus one texture warp per camera.

    The cars get random commands like the env benchmark's, and are put back on
    the grid every 60 steps so that they keep touching as often.
    """
    env = RaceEnv(num_cars=num_cars, obstacles=OBSTACLES, max_steps=2000)
    env.reset(seed=seed)
    world, renderer = env.world, env._renderer
    ground = renderer._ground
    size = (env.camera.width, env.camera.height)
    homographies = [renderer.ground_homography(camera_pose(env.camera, world.poses[i])) for i in range(num_cars)]
    rng = np.random.default_rng(seed)
    table = np.array([(np.radians(s), v) for s, v in env.actions.actions])
    count = [0]

    def step():
        world.step(table[rng.integers(len(table), size=env.total_cars)])
        for homography in homographies:
            cv2.warpPerspective(ground, homography, size, flags=cv2.INTER_NEAREST)
        count[0] += 1
        if count[0] % 60 == 0:
            env.reset()

    rate = _best_rate(step, num_cars, seconds)
    env.close()
    return rate


def _bench_workers(num_workers: int, num_cars: int, seconds: float) -> float:
    """Agent-steps per second of `num_workers` env processes stepped in lock-step."""
    from .vector import SubprocVectorEnv

    make = functools.partial(RaceEnv, num_cars=num_cars, obstacles=OBSTACLES, max_steps=2000)
    vec = SubprocVectorEnv([make] * num_workers, info_keys=())
    rng = np.random.default_rng(0)
    try:
        vec.reset(seeds=list(range(num_workers)))
        vec.step(rng.integers(10, size=(num_workers, num_cars)))
        return _best_rate(lambda: vec.step(rng.integers(10, size=(num_workers, num_cars))),
                          num_workers * num_cars, seconds)
    finally:
        vec.close()


def run_bench(seconds: float = 3.0, replay_seconds: float = 60.0, progress=print) -> dict:
    """All figures of the benchmark; `seconds` is the time spent per measurement."""
    cv2.setNumThreads(1)  # one core per process, as in training workers
    figures: dict = {"agent_steps_per_s": {"fast": {}, "pybullet": {}, "floor": {}}}
    per_s = figures["agent_steps_per_s"]
    for n in CAR_COUNTS:
        per_s["fast"][str(n)] = round(_bench_env(n, "fast", seconds), 1)
        progress(f"fast renderer, {n} cars: {per_s['fast'][str(n)]:.0f} agent-steps/s")
    for n in (1, 4):
        per_s["pybullet"][str(n)] = round(_bench_env(n, "pybullet", seconds), 1)
        progress(f"pybullet renderer, {n} cars: {per_s['pybullet'][str(n)]:.0f} agent-steps/s")
    for n in (1, 4):
        per_s["floor"][str(n)] = round(_bench_floor(n, seconds), 1)
        progress(f"floor (physics + one warp per camera), {n} cars: {per_s['floor'][str(n)]:.0f} agent-steps/s")
    fast4 = per_s["fast"]["4"]
    figures["fast_over_pybullet_4"] = round(fast4 / per_s["pybullet"]["4"], 1)
    figures["fast_over_floor_4"] = round(fast4 / per_s["floor"]["4"], 3)
    per_agent_us = {n: 1e6 / per_s["fast"][str(n)] for n in CAR_COUNTS}
    figures["per_agent_cost_growth_1_to_8"] = round(per_agent_us[8] / per_agent_us[1], 3)
    one = _bench_workers(1, 4, seconds)
    two = _bench_workers(2, 4, seconds)
    figures["workers_agent_steps_per_s"] = {"1": round(one, 1), "2": round(two, 1)}
    figures["workers_speedup_2"] = round(two / one, 3)
    progress(f"worker processes, 4 cars each: 1 -> {one:.0f}, 2 -> {two:.0f} agent-steps/s")
    if replay_seconds:
        from .replay import replay_cost

        cost = replay_cost(seconds=replay_seconds, repeats=1)
        figures["replay"] = cost
        progress(f"replay of a 4-car {replay_seconds:g} s race: {cost['replay_mb']} MB, "
                 f"+{cost['overhead_percent']}% race time")
    figures["peak_rss_mb"] = round(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024, 1)
    return figures


def format_table(figures: dict) -> list[tuple[str, str]]:
    """(label, value) rows for printing."""
    per_s = figures["agent_steps_per_s"]
    rows = [(f"fast, {n} cars (agent-steps/s)", f"{v:,.0f}") for n, v in per_s["fast"].items()]
    rows += [(f"pybullet, {n} cars (agent-steps/s)", f"{v:,.0f}") for n, v in per_s["pybullet"].items()]
    rows += [(f"floor, {n} cars (agent-steps/s)", f"{v:,.0f}") for n, v in per_s["floor"].items()]
    rows += [
        ("fast / pybullet, 4 cars", f"{figures['fast_over_pybullet_4']}x"),
        ("fast / floor, 4 cars", f"{figures['fast_over_floor_4']}"),
        ("per-agent cost, 8 cars / 1 car", f"{figures['per_agent_cost_growth_1_to_8']}x"),
        ("2 workers / 1 worker", f"{figures['workers_speedup_2']}x"),
        ("peak RSS (MB)", f"{figures['peak_rss_mb']}"),
    ]
    if "replay" in figures:
        replay = figures["replay"]
        rows.append((f"replay, 4 cars, {replay['steps'] / 15:g} s race", f"{replay['replay_mb']} MB, "
                     f"+{replay['overhead_percent']}% time"))
    return rows
