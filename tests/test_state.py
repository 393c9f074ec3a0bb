"""Privileged state: PettingZoo's `state()` for centralised critics and the `observation="state"` env of RL
teachers (environment/state.py)."""
import math

import numpy as np
import pytest
from pettingzoo.test import parallel_api_test
from pettingzoo.test.state_test import state_test

import multirace
from multirace.environment.state import CAR_FEATURES, GLOBAL_PER_CAR, LOOKAHEAD

CONTINUOUS = {"action_space_type": "continuous",
              "action_space": {"steering_angle": {"low": -30, "high": 30}, "speed": {"low": 0.5, "high": 4.0}}}


def test_state_passes_pettingzoo_state_test():
    """PettingZoo's own state test: state() in state_space at every step of the AEC and parallel forms."""
    config = dict(num_cars=2, bots=("follow@1.0",), obstacles=1, max_steps=60)
    state_test(multirace.env(**config), multirace.parallel_env(**config), num_cycles=40)


def test_state_holds_every_car_learning_cars_then_bots():
    env = multirace.parallel_env(num_cars=2, bots=("follow@1.5",), race="head_to_head", max_steps=200)
    env.reset(seed=3)
    assert env.state_space.shape == (3 * GLOBAL_PER_CAR,)
    for _ in range(40):
        env.step({a: 4 for a in env.agents})  # straight on at 1 m/s
    rows = env.state().reshape(3, GLOBAL_PER_CAR)
    assert (rows[:, 0] == 1.0).all(), "every car is racing"
    bot = rows[2]
    assert bot[5] * 4.0 == pytest.approx(env.world.drive_speed[2], abs=0.05), "the bot's forward speed, scaled"
    assert bot[8] > rows[0][8] - 0.2, "race distance (laps) is carried per car"
    np.testing.assert_allclose(rows[:, 3] ** 2 + rows[:, 4] ** 2, 1.0, atol=1e-5)  # cos, sin of the yaw


def test_state_observations_render_nothing_and_match_the_env():
    env = multirace.parallel_env(num_cars=2, observation="state", action_space=CONTINUOUS, max_steps=50)
    parallel_api_test(env, num_cycles=50)
    obs, _ = env.reset(seed=0)
    assert env.renderer is None, "a state env never builds a camera renderer"
    x = obs["car_0"]
    assert x.shape == (CAR_FEATURES,) and x.dtype == np.float32
    assert env.observation_space("car_0").contains(x)
    # on the grid, at rest, facing along the track: the centre line ahead lies ahead of the car
    ahead_x = x[11:11 + len(LOOKAHEAD)]
    assert (ahead_x > 0.8).all()
    assert x[0] == pytest.approx(0.0, abs=1e-3), "at rest"


def test_state_lateral_offset_sign_follows_the_road():
    """A car moved to the left half of the road reads a positive offset, one on the right a negative one."""
    env = multirace.parallel_env(num_cars=2, observation="state", action_space=CONTINUOUS)
    env.reset(seed=0)
    obs = env.move_cars({0: (5.0, 0.2), 1: (8.0, -0.2)})
    assert obs["car_0"][6] > 0.2 and obs["car_1"][6] < -0.2
    assert math.isclose(obs["car_0"][10], 1.0, abs_tol=1e-3), "placed along the track: no heading error"


def test_state_observation_keyword_is_checked():
    with pytest.raises(ValueError, match="observation"):
        multirace.parallel_env(observation="lidar")


def test_the_ego_view_shows_the_cars_most_in_the_way_not_merely_the_nearest():
    """In a pack, a car in line 0.6 m ahead is shown before one 0.1 m ahead but well clear to the side (which
    a teacher that saw only the two nearest drove into, lapping a pack)."""
    from multirace.environment.state import TRAFFIC_RANGE

    env = multirace.parallel_env(num_cars=4, observation="state", action_space=CONTINUOUS, race="head_to_head")
    env.reset(seed=0)
    obs = env.move_cars({0: (5.0, 0.3), 1: (5.1, -0.25), 2: (5.4, -0.05), 3: (5.6, 0.3)}, clear=False)
    traffic = obs["car_0"][11 + 2 * len(LOOKAHEAD):].reshape(3, 4)  # two ahead, one behind
    first, second, behind = traffic
    assert first[0] == 1.0 and first[1] * TRAFFIC_RANGE == pytest.approx(0.6, abs=0.05)  # car 3, in line
    assert first[2] == pytest.approx(0.0, abs=0.02)
    assert second[1] * TRAFFIC_RANGE == pytest.approx(0.4, abs=0.05)  # car 2, half a car width beyond touching
    assert second[2] == pytest.approx(-0.35, abs=0.02)
    assert behind[0] == 0.0  # nobody behind car 0
    assert obs["car_3"][11 + 2 * len(LOOKAHEAD):].reshape(3, 4)[2][1] * TRAFFIC_RANGE == pytest.approx(0.2, abs=0.05)


def test_the_camera_view_lists_only_the_cars_the_front_camera_shows():
    """``state_view="camera"``: a car alongside and a car behind are out of the front camera's field of view, so
    out of the traffic rows, while the default view lists them; the car in line ahead is in both."""
    from multirace.environment.state import TRAFFIC_RANGE

    slots = {0: (5.0, 0.0), 1: (5.05, 0.3), 2: (6.0, 0.0), 3: (4.2, 0.0)}  # alongside, 1 m ahead, 0.8 m behind
    rows = {}
    for view in ("all", "camera"):
        env = multirace.parallel_env(num_cars=4, observation="state", state_view=view, action_space=CONTINUOUS,
                                     race="head_to_head")
        env.reset(seed=0)
        rows[view] = env.move_cars(slots, clear=False)["car_0"][11 + 2 * len(LOOKAHEAD):].reshape(3, 4)
        np.testing.assert_array_equal(env.car_state(0, view), env.move_cars(slots, clear=False)["car_0"])
        env.close()
    first, second, behind = rows["all"]
    assert first[0] == second[0] == behind[0] == 1.0
    assert first[1] * TRAFFIC_RANGE < 0.15 and first[2] == pytest.approx(0.3, abs=0.02)  # car 1, alongside
    assert behind[1] * TRAFFIC_RANGE == pytest.approx(0.8, abs=0.05)
    first, second, behind = rows["camera"]
    assert first[0] == 1.0 and first[1] * TRAFFIC_RANGE == pytest.approx(1.0, abs=0.05)  # car 2 only
    assert second[0] == 0.0 and behind[0] == 0.0


def test_a_car_shows_in_the_camera_from_any_part_of_its_body():
    """`in_camera_view`: a car whose centre lies just outside the field of view but whose nose is inside it
    shows; one entirely outside does not; nor does a car ahead of the body centre but behind the lens."""
    from types import SimpleNamespace

    from multirace.environment.state import in_camera_view
    from multirace.sensors.camera import CameraSpec
    from multirace.sim.car import CarSpec

    camera, spec = CameraSpec(), CarSpec()
    me = SimpleNamespace(x=0.0, y=0.0, yaw=0.0)
    edge = math.tan(camera.hfov / 2)  # sideways metres per metre ahead of the lens at the field's edge
    lens = camera.forward

    def car(ahead, aside, yaw=0.0):
        return SimpleNamespace(x=lens + ahead, y=aside, yaw=yaw)

    assert in_camera_view(camera, me, car(1.0, 0.0), spec)
    centre_out = edge * 1.0 + 0.05  # centre 5 cm outside the edge; the near side of the body 5 cm inside
    assert in_camera_view(camera, me, car(1.0, centre_out), spec)
    assert not in_camera_view(camera, me, car(1.0, edge * 1.5 + spec.width), spec)
    assert not in_camera_view(camera, me, car(-spec.length / 2 - 0.01, 0.0), spec)  # its nose just behind the lens
    assert in_camera_view(camera, me, car(0.05, 0.0), spec), "a car filling the view, corners outside it"
