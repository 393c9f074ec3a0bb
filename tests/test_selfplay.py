"""Self-play's pool opponents are drivers: one car through `drive`, many in one net pass through `drive_batch`,
each through its own action space; in training their commands reach the env as commands, not quantised to the
learner's actions."""
from __future__ import annotations

import json
import math
import shutil

import numpy as np
import pytest

from multirace.environment.actions import load_action_space
from multirace.environment.actions import Command
from multirace.environment.drivers import Driver
from multirace.environment.race_env import RaceEnv
from multirace.racing.agentfile import load_agent
from multirace.racing.policy import Policy
from multirace.sim.car import CarSpec
from multirace.train.config import SHIPPED_AGENTS, make_config
from multirace.train.selfplay import Opponent, OpponentPool

# a learner with one action, hard left at a crawl: any opponent command quantised to it would steer 30 degrees
ONE_ACTION = {"action_space": [{"steering_angle": 30.0, "speed": 0.1}], "action_space_type": "discrete"}
STEER_TOLERANCE = 3.0  # degrees: five sigmas of DeepRacer's steering noise (0.01 rad) the env adds
SPEED_TOLERANCE = 0.5  # m/s: five sigmas of its speed noise (0.1 m/s)


@pytest.fixture(scope="module")
def racer():
    """The shipped racer: a camera net with a continuous action space."""
    return load_agent(SHIPPED_AGENTS / "racer.pt", step_budget=None)


def test_an_opponent_drives_a_car_of_a_race_env_through_drive(racer):
    opponent = Opponent(racer.name, racer.net, racer.action_space, "shipped")
    assert isinstance(opponent, Driver)
    env = RaceEnv(track="Oval_track", num_cars=2, action_space=ONE_ACTION)
    try:
        obs, _ = env.reset(seed=4)
        for _ in range(4):
            command = opponent.drive(env.race_state, 1, obs["car_1"])
            assert command == Policy(racer).command(obs["car_1"])  # its net, then its own action space's greedy command
            obs, *_ = env.step({"car_0": 0, "car_1": Command(command)})
            steer, speed = env.race_state.cars[1].command  # the env took the command, whatever its action space
            assert abs(math.degrees(steer) - command[0]) < STEER_TOLERANCE
            assert abs(speed - command[1]) < SPEED_TOLERANCE
            assert abs(math.degrees(env.race_state.cars[0].command[0]) - 30.0) < STEER_TOLERANCE  # the learner's action
        batch = opponent.drive_batch(np.stack([obs["car_0"], obs["car_1"]]))  # one pass, the same commands
        np.testing.assert_allclose(batch, [opponent.drive(None, car, obs[f"car_{car}"]) for car in (0, 1)],
                                   rtol=1e-5, atol=1e-4)
    finally:
        env.close()


def test_in_training_a_continuous_opponents_commands_reach_the_env_unquantised(racer, tmp_path):
    from multirace.train.ppo import make_vector_env, observation_shapes

    space_file = tmp_path / "one_action.json"
    space_file.write_text(json.dumps(ONE_ACTION))
    shipped = tmp_path / "shipped"
    shipped.mkdir()
    shutil.copy(SHIPPED_AGENTS / "racer.pt", shipped)
    config = make_config("tiny", tracks=("Oval_track",), action_space=str(space_file), opponent_pool=True,
                         deepracer_log=True, seed=2)
    vec = make_vector_env(config)  # TrainEnvs in a worker process; with deepracer_log each car's sim-trace row comes back
    try:
        obs, _ = vec.reset(seeds=[5])
        _, image_shape, vectors = observation_shapes(obs, 1)
        pool = OpponentPool(config, load_action_space(config.action_space), image_shape, np.random.default_rng(0),
                            shipped_dir=shipped, vector_inputs=vectors)
        assert [member.name for member in pool.members] == [racer.name]
        mask = pool.assign(1, config.cars_per_env)
        assert mask.tolist() == [[True, True, True, False]]
        learner_path = []
        for _ in range(5):
            commands = pool.commands(obs, mask)
            assert np.isnan(commands[0, :3]).all()  # the learner's cars take their actions
            steer, speed = commands[0, 3]
            assert abs(steer - 30.0) > 2 * STEER_TOLERANCE  # far from the learner's one action
            obs, _, _, _, infos = vec.step(np.zeros(mask.shape, np.int64), commands)
            # the sim-trace rows: the opponent's steer and throttle as executed, the learner's as commanded
            opponent_row, learner_row = (infos[0][car]["deepracer"].text.split(",") for car in (3, 0))
            assert abs(float(opponent_row[4]) - steer) < STEER_TOLERANCE
            assert abs(float(opponent_row[5]) - speed) < SPEED_TOLERANCE
            assert opponent_row[6] == f"[{opponent_row[4]} {opponent_row[5]}]"  # a command, no action index
            assert learner_row[6] == "0"  # the learner's car took its action index
            learner_path.append([float(v) for v in learner_row[1:4]])  # X, Y, yaw (degrees)
        # what the learner's car executed, from its path: the curvature it drove gives its steering angle
        (x0, y0, yaw0), (x1, y1, yaw1) = learner_path[1], learner_path[-1]
        curvature = math.radians(yaw1 - yaw0) / math.hypot(x1 - x0, y1 - y0)
        assert abs(math.degrees(math.atan(curvature * CarSpec().wheelbase)) - 30.0) < 2 * STEER_TOLERANCE
    finally:
        vec.close()


def test_a_tiny_training_run_with_the_pool_leaves_the_opponents_cars_out_of_the_learners_samples(tmp_path):
    from multirace.train.ppo import train

    config = make_config("tiny", tracks=("Oval_track",), opponent_pool=True, max_iterations=2, minutes=10, seed=1,
                         rollout_steps=32, minibatch_size=32, progress=False, deepracer_log=False)
    summary = train(config, tmp_path / "pool.pt")
    assert summary["iterations"] == 2
    assert summary["agent_steps"] == 2 * 32 * 3  # the shipped agents drive one car of the four
