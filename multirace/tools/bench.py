"""`multirace bench`: throughput figures and ratios, all from one run.

Measures agent-steps per second (one car's observation, reward and info per
15 Hz step) of the full env (cameras, physics with collisions, obstacles,
random actions, full reward params and infos) for 1, 2, 4 and 8 cars with the
fast renderer and with the PyBullet renderer, for 4 cars with the LIDAR
scanned too, for 4 cars on the kinematic car model (`kinematic`, beside
the default tyre model) and for 4 cars with PyBullet stepped in every step
(`no_shortcut`, beside the contact shortcut); the floor (the same run's
physics steps alone, replayed, plus one bare texture warp per camera); the
same two for 4 cars driven as a head-to-head race (`racing`: no boxes, bots
that keep their gaps, where the random drivers push each other in a bunch
round the boxes); the share of steps that stepped PyBullet; the fast
renderer alone (one camera, frames per second in the same interleaved
windows); the per-agent cost of 8 cars against 1 over the same recorded
random steps (whole runs), and by the windows with the share of PyBullet
steps in each one's best window (a lone random car's cheapest window is
where it drove free of the boxes); the speed-up of two
worker processes over one; memory; and the cost of recording a replay.
`run_profile` is `multirace bench --profile`: where a step's time goes, and
its floor's (`profile.py`).
"""
from __future__ import annotations

import functools
import resource
import time

import cv2
import numpy as np

from ..environment.actions import Command
from ..environment.bots import parse_bot
from ..environment.race_env import RaceEnv
from ..sensors.camera import camera_pose
from .profile import profile_floor, profile_step, renderer_frames_per_s, renderer_step

CAR_COUNTS = (1, 2, 4, 8)
WINDOWS = 30  # each figure is the best of this many equal time windows, taken in turns
WARM_UP = 0.1  # untimed lead-in of each window, as a share of the window
OBSTACLES = 3
RACING_BOTS = ("follow@2.2", "follow@1.8", "follow@1.4", "follow@1.0")  # `racing`'s drivers, fastest first
RACING_STEPS = 900  # steps of its recorded race (60 s), replayed in a loop
CARS_PER_WORKER = 4  # cars in each env of the worker-process figures
SAME_STEPS = 900  # steps of the recorded random run each car count drives whole for `_same_steps_costs`
SAME_STEPS_RUNS = 9  # whole runs of it timed per car count, in turns


def _interleaved_rates(workloads: dict, seconds: float, windows: int = WINDOWS,
                       worlds: dict | None = None) -> tuple[dict, dict]:
    """Agent-steps per wall-clock second and per CPU second of this thread, of each workload; and, for the
    workloads named in `worlds` (name -> the `World` they step), the share of the steps of their best CPU
    window that stepped PyBullet.

    `workloads` maps a name to (step function, agents per step). Each figure is
    the best of several short windows (other processes on a 2-core machine slow
    some windows down, and the best is the closest to what the code costs), and
    the windows of all workloads take turns, so that a slow patch of the
    machine hits them alike and their ratios stay meaningful. Each window
    starts with an untimed lead-in (`WARM_UP`), so that a workload whose worker
    processes slept through the other windows is timed awake. The CPU figure
    does not count time spent waiting for a core.
    """
    worlds = worlds or {}
    best = {name: (0.0, 0.0) for name in workloads}
    best_share = {}
    for _ in range(windows):
        for name, (step, agents_per_step) in workloads.items():
            warm_up = time.perf_counter() + WARM_UP * seconds / windows
            while time.perf_counter() < warm_up:  # untimed: wake the workload's processes, refill its caches
                step()
            world = worlds.get(name)
            counts = (world.bullet_steps, world.action_steps) if world is not None else None
            steps, start, start_cpu = 0, time.perf_counter(), time.thread_time()
            while time.perf_counter() - start < seconds / windows:
                step()
                steps += 1
            wall, cpu = time.perf_counter() - start, time.thread_time() - start_cpu
            best_wall, best_cpu = best[name]
            cpu_rate = agents_per_step * steps / max(cpu, 1e-9)
            if world is not None and cpu_rate > best_cpu:
                best_share[name] = (world.bullet_steps - counts[0]) / max(world.action_steps - counts[1], 1)
            best[name] = (max(best_wall, agents_per_step * steps / wall), max(best_cpu, cpu_rate))
    return best, best_share


def _random_driving(num_cars: int, renderer: str = "fast", seed: int = 0, lidar: bool = False,
                    dynamics: str = "dynamic", shortcut: bool = True):
    """The benchmark's env, reset, and a step function driving it with random actions (resetting when done).

    `shortcut` False steps PyBullet in every step (`World.contact_shortcut`)."""
    env = RaceEnv(num_cars=num_cars, obstacles=OBSTACLES, renderer=renderer, max_steps=2000, lidar=lidar,
                  dynamics=dynamics)
    env.world.contact_shortcut = shortcut
    rng = np.random.default_rng(seed)
    env.reset(seed=seed)
    n_actions = env.actions.space.n

    def step():
        if not env.agents:
            env.reset()
        env.step({a: int(rng.integers(n_actions)) for a in env.agents})

    return env, step


def _replayed_random(num_cars: int, seed: int = 0, steps: int = SAME_STEPS):
    """`_random_driving`'s env and a function that drives the same run every call: from ``reset(seed=seed)``,
    the first `steps` random actions of that env's run (the steps the floors replay), recorded once. The
    function returns how many agent-steps it drove."""
    env = RaceEnv(num_cars=num_cars, obstacles=OBSTACLES, max_steps=2000)
    rng = np.random.default_rng(seed)
    env.reset(seed=seed)
    script = []
    while env.agents and len(script) < steps:
        script.append({a: int(rng.integers(env.actions.space.n)) for a in env.agents})
        env.step(script[-1])

    def run() -> int:
        env.reset(seed=seed)
        agent_steps = 0
        for actions in script:
            env.step(actions)
            agent_steps += len(actions)
        return agent_steps

    return env, run


def _same_steps_costs(car_counts=(1, 8), runs: int = SAME_STEPS_RUNS) -> dict:
    """CPU microseconds per agent-step of the env at each car count over one recorded run
    (`_replayed_random`), the best of `runs` whole runs each, taken in turns: every timing covers the same
    steps, so the best is the code's cost, not the luck of a window that caught a cheaper stretch of the
    run (a lone random car is pinned against a box in most steps, PyBullet stepped, and drives free in
    others at a quarter of the cost)."""
    drivers = {n: _replayed_random(n) for n in car_counts}
    best = dict.fromkeys(car_counts, float("inf"))
    try:
        for _ in range(runs):
            for n, (env, run) in drivers.items():
                start = time.thread_time()
                agent_steps = run()
                best[n] = min(best[n], 1e6 * (time.thread_time() - start) / agent_steps)
    finally:
        for env, _ in drivers.values():
            env.close()
    return best


def _racing(num_cars: int, seed: int = 0, steps: int = RACING_STEPS):
    """The benchmark's env driven as a head-to-head race rather than a scrum: no boxes (the bots do not avoid
    them), its cars follow `RACING_BOTS`' commands (each keeps its gap to the car ahead), recorded once and
    replayed, so the step function costs the env alone. Returns the env, reset, and the step function (which
    starts the recording over at its end)."""
    env = RaceEnv(num_cars=num_cars, max_steps=steps, laps=1000)
    bots = [parse_bot(f"bot:{RACING_BOTS[i % len(RACING_BOTS)]}") for i in range(num_cars)]
    env.reset(seed=seed)
    script = []
    while env.agents:
        state = env.race_state
        script.append({agent: Command(bots[i].drive(state, i)) for i, agent in enumerate(env.agents)})
        env.step(script[-1])
    env.reset(seed=seed)
    position = [0]

    def step():
        if position[0] == len(script):
            env.reset(seed=seed)
            position[0] = 0
        env.step(script[position[0]])
        position[0] += 1

    return env, step


def _env_stepper(num_cars: int, renderer: str, seed: int = 0, lidar: bool = False, dynamics: str = "dynamic",
                 shortcut: bool = True, racing: bool = False):
    """(step, close) of the env with random actions (`racing`: driven as a race, `_racing`); `step.env` is
    the env."""
    env, step = _racing(num_cars, seed) if racing else _random_driving(num_cars, renderer, seed, lidar, dynamics,
                                                                       shortcut)
    step()  # warm-up
    step.env = env
    return step, env.close


def _floor_stepper(num_cars: int, seed: int = 0, steps: int = 900, racing: bool = False):
    """(step, close) of the bare minimum of the env benchmark's run: its physics alone plus one texture warp per camera
    (`step.world` is the world it steps).

    A run of the env benchmark (same cars, obstacles, random actions or `racing` drivers, and seed)
    is recorded first: the commands of every physics step, and every time a car
    or box is put somewhere (an off-track car reset onto the track, say). The
    floor replays exactly that into the world alone, in a loop, so its PyBullet
    work, collisions included, is the env's; each step then warps one bare
    image per camera.
    """
    env, drive = _racing(num_cars, seed) if racing else _random_driving(num_cars, seed=seed)
    world = env.world
    start = (world.poses.tolist(), world.obstacle_poses.tolist())
    actions = {name: getattr(world, name) for name in ("place_car", "park", "place_obstacle", "step")}
    script, moves = [], []  # per step: (moves since the last physics step, commands)

    def recorder(name):
        def record(*args):
            if name == "step":
                script.append((list(moves), np.array(args[0])))
                moves.clear()
            else:
                moves.append((name, args))
            return actions[name](*args)
        return record

    for name in actions:
        setattr(world, name, recorder(name))
    for _ in range(steps):
        drive()
    for name in actions:
        delattr(world, name)  # the world's own methods again
    world.contact_shortcut = False  # the floor is PyBullet's world stepped in every step, as before the shortcut

    def restart():
        car_poses, obstacle_poses = start
        for i, pose in enumerate(car_poses):
            world.place_car(i, *pose)
        for k, pose in enumerate(obstacle_poses):
            world.place_obstacle(k, *pose)

    renderer = env.renderer
    ground = renderer._ground
    size = (env.camera.width, env.camera.height)
    homographies = [renderer.ground_homography(camera_pose(env.camera, world.poses[i])) for i in range(num_cars)]
    position = [0]
    restart()

    def step():
        placements, commands = script[position[0]]
        for name, args in placements:
            getattr(world, name)(*args)
        world.step(commands)
        for homography in homographies:
            cv2.warpPerspective(ground, homography, size, flags=cv2.INTER_NEAREST)
        position[0] = (position[0] + 1) % len(script)
        if position[0] == 0:
            restart()

    step.world = world
    return step, env.close


def _workers_stepper(num_workers: int, num_cars: int):
    """(step, close) of `num_workers` env processes stepped in lock-step."""
    from ..environment.vector import SubprocVectorEnv

    make = functools.partial(RaceEnv, num_cars=num_cars, obstacles=OBSTACLES, max_steps=2000)
    vec = SubprocVectorEnv([make] * num_workers, info_keys=())
    rng = np.random.default_rng(0)
    vec.reset(seeds=list(range(num_workers)))

    def step():
        vec.step(rng.integers(10, size=(num_workers, num_cars)))

    step()
    return step, vec.close


def _resident_mb() -> float:
    """This process's resident memory now, MB (Linux)."""
    with open("/proc/self/statm") as statm:
        return int(statm.read().split()[1]) * resource.getpagesize() / 2**20


def run_bench(seconds: float = 3.0, replay_seconds: float = 240.0, progress=print,
              training_seconds: float = 40.0) -> dict:
    """All figures of the benchmark; `seconds` is the time spent per measurement."""
    cv2.setNumThreads(1)  # one core per process, as in training workers
    steppers = {("fast", 1): _env_stepper(1, "fast")}  # loads the compiled kernels once
    before = _resident_mb()
    steppers[("fast", 4)] = _env_stepper(4, "fast")
    env_mb = _resident_mb() - before
    steppers.update({("fast", n): _env_stepper(n, "fast") for n in CAR_COUNTS if n not in (1, 4)})
    steppers.update({("pybullet", n): _env_stepper(n, "pybullet") for n in (1, 4)})
    steppers[("lidar", 4)] = _env_stepper(4, "fast", lidar=True)
    steppers[("kinematic", 4)] = _env_stepper(4, "fast", dynamics="kinematic")
    steppers[("no_shortcut", 4)] = _env_stepper(4, "fast", shortcut=False)
    steppers.update({("floor", n): _floor_stepper(n) for n in (1, 4)})
    steppers[("racing", 4)] = _env_stepper(4, "fast", racing=True)
    steppers[("floor_racing", 4)] = _floor_stepper(4, racing=True)
    steppers.update({("workers", n): _workers_stepper(n, CARS_PER_WORKER) for n in (1, 2)})
    steppers[("renderer", 1)] = (renderer_step(steppers[("fast", 4)][0].env), lambda: None)  # frames, not agents
    try:
        workloads = {key: (step, key[1] * CARS_PER_WORKER if key[0] == "workers" else key[1])
                     for key, (step, _) in steppers.items()}
        progress(f"measuring {len(workloads)} workloads, {WINDOWS} interleaved windows each ...")
        worlds = {key: steppers[key][0].env.world for key in (("fast", 1), ("fast", 4), ("fast", 8), ("racing", 4))}
        before = {key: (world.bullet_steps, world.action_steps) for key, world in worlds.items()}
        rates, best_window_share = _interleaved_rates(workloads, seconds, worlds=worlds)
        pybullet_share = {key: (world.bullet_steps - before[key][0]) / max(world.action_steps - before[key][1], 1)
                          for key, world in worlds.items()}
    finally:
        for _, close in steppers.values():
            close()
    kinds = ("fast", "pybullet", "lidar", "kinematic", "no_shortcut", "floor", "racing", "floor_racing")
    figures: dict = {"agent_steps_per_s": {kind: {} for kind in kinds},
                     "agent_steps_per_cpu_s": {kind: {} for kind in kinds}}
    per_s, per_cpu_s = figures["agent_steps_per_s"], figures["agent_steps_per_cpu_s"]
    for kind in kinds:
        for (name, n), (wall, cpu) in sorted(rates.items()):
            if name == kind:
                per_s[kind][str(n)], per_cpu_s[kind][str(n)] = round(wall, 1), round(cpu, 1)
                progress(f"{kind}, {n} cars: {wall:.0f} agent-steps/s ({cpu:.0f} per CPU second)")
    for suffix, rates_of in (("", per_s), ("_cpu", per_cpu_s)):
        figures["fast_over_pybullet_4" + suffix] = round(rates_of["fast"]["4"] / rates_of["pybullet"]["4"], 1)
        figures["fast_over_floor_4" + suffix] = round(rates_of["fast"]["4"] / rates_of["floor"]["4"], 3)
        figures["lidar_over_fast_4" + suffix] = round(rates_of["lidar"]["4"] / rates_of["fast"]["4"], 3)
        figures["dynamic_over_kinematic_4" + suffix] = round(rates_of["fast"]["4"] / rates_of["kinematic"]["4"], 3)
        figures["shortcut_gain_4" + suffix] = round(rates_of["fast"]["4"] / rates_of["no_shortcut"]["4"], 3)
        figures["racing_over_floor_4" + suffix] = round(rates_of["racing"]["4"] / rates_of["floor_racing"]["4"], 3)
    figures["pybullet_step_share_4"] = round(pybullet_share[("fast", 4)], 3)
    figures["pybullet_step_share_racing_4"] = round(pybullet_share[("racing", 4)], 3)
    renderer_fps = rates[("renderer", 1)][0]
    figures["renderer_frames_per_s"] = round(renderer_fps, 1)
    progress(f"PyBullet stepped in {100 * pybullet_share[('fast', 4)]:.0f} % of the 4-car env's steps (random "
             f"drivers), {100 * pybullet_share[('racing', 4)]:.0f} % when they race; renderer alone: "
             f"{renderer_fps:.0f} frames/s")
    per_agent_us = {n: 1e6 / per_cpu_s["fast"][str(n)] for n in CAR_COUNTS}
    figures["per_agent_cost_growth_1_to_8"] = round(per_agent_us[8] / per_agent_us[1], 3)
    # what the windows' figure compares: the share of PyBullet steps in each car count's best window and overall
    figures["pybullet_step_share_best_window"] = {str(n): round(best_window_share[("fast", n)], 3) for n in (1, 8)}
    figures["pybullet_step_share_windows"] = {str(n): round(pybullet_share[("fast", n)], 3) for n in (1, 8)}
    same_steps = _same_steps_costs()
    figures["per_agent_us_same_steps"] = {str(n): round(us, 1) for n, us in same_steps.items()}
    figures["per_agent_cost_growth_1_to_8_same_steps"] = round(same_steps[8] / same_steps[1], 3)
    progress(f"per-agent CPU cost over the same {SAME_STEPS} random steps: 1 car {same_steps[1]:.1f} us, "
             f"8 cars {same_steps[8]:.1f} us ({figures['per_agent_cost_growth_1_to_8_same_steps']}x)")
    one, two = rates[("workers", 1)][0], rates[("workers", 2)][0]
    figures["workers_agent_steps_per_s"] = {"1": round(one, 1), "2": round(two, 1)}
    figures["workers_speedup_2"] = round(two / one, 3)
    progress(f"worker processes, 4 cars each: 1 -> {one:.0f}, 2 -> {two:.0f} agent-steps/s")
    figures["env_memory_mb_4_cars"] = round(env_mb, 1)
    if replay_seconds:
        from .replay_cost import replay_cost

        # the median of 9 pairs of races in turns: a busy host slows a few seconds at a time, so slow pairs come
        # in runs, and the median of more pairs depends less on when the run fell
        cost = replay_cost(seconds=replay_seconds, repeats=9)
        figures["replay"] = cost
        progress(f"replay of a 4-car {replay_seconds:g} s race: {cost['replay_mb']} MB, "
                 f"race speed -{cost['speed_loss_percent']}%")
    if training_seconds:  # the full PPO loop (sampling + updates) on 2 worker processes
        from ..train.throughput import training_throughput

        for key, preset in (("training", "fast"), ("training_throughput", "throughput")):
            figures[key] = training = training_throughput(seconds=training_seconds, preset=preset)
            progress(f"training (PPO, sampling + updates, 2 workers, --config {preset}): "
                     f"{training['agent_steps_per_s']:.0f} agent-steps/s "
                     f"({100 * training['sampling_share']:.0f} % of the time sampling, "
                     f"{100 * training['update_share']:.0f} % updating; "
                     f"{training['cpu_us_per_agent_step']} CPU us per agent-step)")
    figures["cli_help_s"] = cli_start_seconds()
    progress(f"`multirace --help`, whole process: {figures['cli_help_s']['median']} s (median)")
    figures["peak_rss_mb"] = round(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024, 1)
    return figures


def run_profile(num_cars: int = 4, steps: int = 3000, progress=print, racing: bool = False) -> dict:
    """The per-stage split of the bench's env step (`num_cars` cars, random actions, or with `racing` the
    `_racing` workload) and the renderer alone."""
    env, step = _racing(num_cars) if racing else _random_driving(num_cars)
    try:
        for _ in range(200):  # untimed lead-in
            step()
        before = (env.world.bullet_steps, env.world.action_steps)
        split = profile_step(step, env, steps)
        pybullet_share = (env.world.bullet_steps - before[0]) / max(env.world.action_steps - before[1], 1)
        fps = renderer_frames_per_s(env)
    finally:
        env.close()
    floor_step, close_floor = _floor_stepper(num_cars, racing=racing)
    try:
        for _ in range(200):  # untimed lead-in
            floor_step()
        floor = profile_floor(floor_step, floor_step.world, steps)
    finally:
        close_floor()
    progress(f"profiled {steps} steps of a {num_cars}-car env ({'racing' if racing else 'random drivers'}) and of "
             f"its floor; renderer alone: {fps:.0f} frames/s")
    return {"cars": num_cars, "steps": steps, "workload": "racing" if racing else "random", "us_per_step": split,
            "floor_us_per_step": floor, "pybullet_step_share": round(pybullet_share, 3),
            "renderer_frames_per_s": round(fps, 1)}


def cli_start_seconds(runs: int = 9) -> dict:
    """Wall time of whole `multirace --help` and `multirace race --help` processes: median, min, max of `runs`."""
    import statistics
    import subprocess
    import sys
    import time

    times = []
    for k in range(runs):
        command = [sys.executable, "-m", "multirace.cli"] + (["race"] if k % 2 else []) + ["--help"]
        start = time.perf_counter()
        subprocess.run(command, check=True, stdout=subprocess.DEVNULL)
        times.append(time.perf_counter() - start)
    return {"median": round(statistics.median(times), 3), "min": round(min(times), 3), "max": round(max(times), 3),
            "runs": runs}


def _percent(share: float) -> str:
    """A share as a whole percentage, "64 %"."""
    return f"{100 * share:.0f} %"


def format_table(figures: dict) -> list[tuple[str, str]]:
    """(label, value) rows for printing."""
    per_s, per_cpu_s = figures["agent_steps_per_s"], figures["agent_steps_per_cpu_s"]
    rows = [(f"{kind}, {n} cars (agent-steps/s; per CPU s)", f"{v:,.0f}; {per_cpu_s[kind][n]:,.0f}")
            for kind in per_s for n, v in per_s[kind].items()]
    rows += [
        ("fast / pybullet, 4 cars (wall; CPU)", f"{figures['fast_over_pybullet_4']}x; "
                                                f"{figures['fast_over_pybullet_4_cpu']}x"),
        ("fast / floor, 4 cars (wall; CPU)", f"{figures['fast_over_floor_4']}; {figures['fast_over_floor_4_cpu']}"),
        ("with LIDAR / without, 4 cars (wall; CPU)", f"{figures['lidar_over_fast_4']}; "
                                                     f"{figures['lidar_over_fast_4_cpu']}"),
        ("tyre model / kinematic model, 4 cars (wall; CPU)", f"{figures['dynamic_over_kinematic_4']}; "
                                                             f"{figures['dynamic_over_kinematic_4_cpu']}"),
        ("with / without the contact shortcut, 4 cars (wall; CPU)", f"{figures['shortcut_gain_4']}; "
                                                                    f"{figures['shortcut_gain_4_cpu']}"),
        ("steps that stepped PyBullet, 4 cars", _percent(figures['pybullet_step_share_4'])),
        ("racing / its floor, 4 cars (wall; CPU)", f"{figures['racing_over_floor_4']}; "
                                                   f"{figures['racing_over_floor_4_cpu']}"),
        ("steps that stepped PyBullet, 4 racing cars", _percent(figures['pybullet_step_share_racing_4'])),
        ("fast renderer alone, 120x160 grey (frames/s)", f"{figures['renderer_frames_per_s']:,.0f}"),
        (f"per-agent CPU cost, 8 cars / 1 car, over the same {SAME_STEPS} random steps (1 car; 8 cars, CPU us "
         "per agent-step)", f"{figures['per_agent_cost_growth_1_to_8_same_steps']}x "
                            f"({figures['per_agent_us_same_steps']['1']}; {figures['per_agent_us_same_steps']['8']})"),
        ("the same, by the best windows (PyBullet stepped in the best window / in all, 1 car; 8 cars)",
         f"{figures['per_agent_cost_growth_1_to_8']}x ({_percent(figures['pybullet_step_share_best_window']['1'])} / "
         f"{_percent(figures['pybullet_step_share_windows']['1'])}; "
         f"{_percent(figures['pybullet_step_share_best_window']['8'])} / "
         f"{_percent(figures['pybullet_step_share_windows']['8'])})"),
        ("2 workers / 1 worker", f"{figures['workers_speedup_2']}x"),
        ("memory of one 4-car env (MB)", f"{figures['env_memory_mb_4_cars']}"),
        ("peak RSS of the bench process (MB)", f"{figures['peak_rss_mb']}"),
        ("`multirace --help`, whole process (s, median)", f"{figures['cli_help_s']['median']}"),
    ]
    for key, label in (("training", "PPO loop, 2 workers"), ("training_throughput", "PPO loop, --config throughput")):
        if key in figures:
            training = figures[key]
            rows.append((f"{label} (agent-steps/s; CPU us per agent-step)",
                         f"{training['agent_steps_per_s']:,.0f}; {training['cpu_us_per_agent_step']} (sampling "
                         f"{100 * training['sampling_share']:.0f} %, updates {100 * training['update_share']:.0f} %)"))
    if "replay" in figures:
        replay = figures["replay"]
        rows.append((f"replay, 4 cars, {replay['steps'] / 15:g} s race", f"{replay['replay_mb']} MB, "
                     f"race speed -{replay['speed_loss_percent']}%"))
    return rows
