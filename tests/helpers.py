"""Shared helpers for the multirace tests (import as `from helpers import ...`)."""
from __future__ import annotations

import hashlib

import cv2
import numpy as np

from multirace.environment.bots import PurePursuit
from multirace.environment.drivers import car_pose
from multirace.environment.race_env import RaceEnv
from multirace.racing.entrant import COMMAND_SPACE, BotController
from multirace.recording.replay_reader import read_chunks

REPLAY_JPEG_QUALITY = 75  # the replay recorder's JPEG quality


def drive_expert(env, speed=1.0, steps=None, lateral=0.0):
    """Drive every learning car with the centre-line pure-pursuit driver until the episode ends.

    Returns the list of per-step info dicts of car_0.
    """
    driver = PurePursuit(speed=speed, lateral=lateral)
    history = []
    count = 0
    while env.agents and (steps is None or count < steps):
        actions, state = {}, env.race_state
        for i, agent in enumerate(env.possible_agents):
            car = state.cars[i]
            steer, spd = driver.command(state.track, state.car_spec, car_pose(car), car.segment)
            actions[agent] = env.actions.nearest(steer, spd)
        _, _, _, _, infos = env.step(actions)
        history.append(infos["car_0"])
        count += 1
    return history


def car_input(image):
    """A camera observation as the car's network input: float32 [1, H, W, C] of raw 0-255 pixels (grey: C = 1)."""
    return np.atleast_3d(image)[None].astype(np.float32)


CONTINUOUS = COMMAND_SPACE  # the full continuous range of DeepRacer commands


def place(env, i, x, y, yaw):
    """Teleport car i to a pose and re-measure it, as if it had driven there (for geometry checks)."""
    env.core.place_cars({i: (x, y, yaw)})


def overflow_on_camera_images(net) -> None:
    """Make a camera net finite on the blank smoke-test image but NaN on real camera images."""
    import torch

    with torch.no_grad():
        for module in net.conv:
            if isinstance(module, torch.nn.Conv2d):
                module.weight.abs_()
                module.bias.zero_()
        net.fc[0].weight.fill_(1e38)
        net.fc[0].bias.zero_()
        net.head.weight.copy_(torch.randn_like(net.head.weight).sign() * 1e38)


class Wild(BotController):
    """A bot that steers hard at full speed for a window of steps (to leave the track)."""

    def __init__(self, spec, window=(30, 60), steer=30.0):
        super().__init__(spec)
        self.window, self.steer = window, steer

    def act(self, observation, info):
        steer, speed = super().act(observation, info)
        lo, hi = self.window
        return (self.steer, 2.0) if lo <= self.env.steps < hi else (steer, speed)


def small_league(name: str = "small", step_budget: float = 0.0667) -> str:
    """A league.toml of one track forward, one seed, the bot:follow@1.5 bot, 1-lap time trials and 2-car heats."""
    return f"""
[league]
name = "{name}"
seeds = [1]
bots = ["bot:follow@1.5"]
step_budget = {step_budget}
replays = false

[[tracks]]
name = "reinvent_base"
directions = ["forward"]

[time_trial]
format = "reset_rule"
laps = 1
trials = 1

[head_to_head]
cars = 2
laps = 1
trials = 1
"""


def seeded_lidar_agent(path, seed=0):
    """A camera + LIDAR agent file with seeded random weights (the 14 actions of agents/action_space_fast.json)."""
    import torch

    from multirace.environment.actions import load_action_space
    from multirace.racing.agentfile import make_metadata, save_agent
    from multirace.racing.nets import DEFAULT_NETWORK, build_net
    from multirace.resources import agents_dir

    space = load_action_space(str(agents_dir() / "action_space_fast.json"))
    torch.manual_seed(seed)
    net = build_net(DEFAULT_NETWORK, (120, 160, 1), space, lidar_samples=64)
    return save_agent(path, net, make_metadata(space, DEFAULT_NETWORK, "lidar_car", lidar=True))



class TorchThreadsEnv(RaceEnv):
    """A race env that loads torch when it steps, as a teacher expert in a training worker does, and reports
    torch's thread count in each car's info (``torch_threads``)."""

    def step(self, actions):
        import torch

        *rest, infos = super().step(actions)
        for info in infos.values():
            info["torch_threads"] = torch.get_num_threads()
        return (*rest, infos)


class Frames:
    """A recorder that keeps each car's pose every step and the JPEG of its camera frame every `every` steps (up to
    the step its run ends)."""

    def __init__(self, every: int):
        self.every, self.poses, self.jpegs = every, {}, {}
        self.shapes = set()  # the shapes of the frames it kept

    def start(self, env):
        self.done = [False] * len(env.race_state.cars)

    def step(self, env, observations, rewards, infos):
        state = env.race_state
        for i, car in enumerate(state.cars):
            self.poses[(i, state.step)] = (car.x, car.y)
            if state.step % self.every == 0 and not self.done[i]:
                image = observations[env.possible_agents[i]]
                self.shapes.add(image.shape)
                if image.ndim == 3:  # colour, RGB: encoded as the writer encodes it
                    image = cv2.cvtColor(image, cv2.COLOR_RGB2BGR)
                jpeg = cv2.imencode(".jpg", image, [cv2.IMWRITE_JPEG_QUALITY, REPLAY_JPEG_QUALITY])[1]
                self.jpegs[(i, state.step)] = hashlib.sha256(jpeg.tobytes()).hexdigest()
            self.done[i] = not car.racing

    def finish(self, env, result):
        pass


def recorded_images(path) -> dict:
    """{(car index, step): sha256 of the JPEG} of every camera image in a replay."""
    found = {}
    for entity, batches in read_chunks(path).items():
        if not entity.startswith("cameras/car_"):
            continue
        car = int(entity.rsplit("_", 1)[1])
        for batch in batches:
            steps = batch.column(batch.schema.get_field_index("step")).to_pylist()
            blobs = batch.column(batch.schema.get_field_index("EncodedImage:blob")).to_pylist()
            for step, blob in zip(steps, blobs):
                assert (car, step) not in found, f"two images of car_{car} at step {step}"
                found[(car, step)] = hashlib.sha256(bytes(blob[0])).hexdigest()
    return found
