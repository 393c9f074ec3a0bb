"""The car's physics: tyres with a grip limit, a drive train with limits, contacts that feed the model."""
import math

import numpy as np
import pytest

import multirace
from multirace.sim import dynamics
from multirace.sim.car import CarSpec
from multirace.sim.dynamics import GRAVITY
from multirace.sim.world import World

SPEC = CarSpec()
DT = 1.0 / 15


def drive(commands, dynamics="dynamic", speed=0.0, steps=None):
    """One car on an empty floor; returns its poses (after each step) and its world."""
    world = World(SPEC, 1, 0, 60, 15, dynamics=dynamics)
    world.connect()
    world.place_car(0, 0.0, 0.0, 0.0, speed=speed)
    poses = []
    for steer, target in commands:
        world.step(np.array([[steer, target]]))
        poses.append(world.poses[0].copy())
    return np.array(poses), world


def path_radius_and_speed(poses):
    """Radius and speed of a stretch of path, from the distance driven and the heading turned."""
    distance = np.linalg.norm(np.diff(poses[:, :2], axis=0), axis=1).sum()
    turned = abs(np.unwrap(poses[:, 2])[-1] - poses[0, 2])
    return distance / turned, distance / ((len(poses) - 1) * DT)


@pytest.mark.parametrize("target", [1.0, 2.0, 3.0, 4.0])
def test_lateral_acceleration_saturates_at_the_friction_limit(target):
    steer = math.radians(20.0)
    poses, _ = drive([(steer, target)] * 60, speed=target)
    radius, speed = path_radius_and_speed(poses[-16:])
    lateral = speed ** 2 / radius
    assert lateral <= 1.05 * SPEC.mu * GRAVITY
    kinematic = speed ** 2 * math.tan(steer) / SPEC.wheelbase
    if kinematic > 1.3 * SPEC.mu * GRAVITY:  # asked for more than the tyres give: held at their limit
        assert lateral > 0.7 * SPEC.mu * GRAVITY
    else:  # within grip: the car goes where its wheels point
        assert radius == pytest.approx(SPEC.wheelbase / math.tan(steer), rel=0.15)


def test_at_top_speed_on_full_lock_the_car_slides_wide():
    lock = SPEC.max_steer
    poses, _ = drive([(lock, 4.0)] * 8, speed=4.0)
    radius, _ = path_radius_and_speed(poses)
    kinematic_radius = SPEC.wheelbase / math.tan(lock)
    assert radius > 4 * kinematic_radius  # 0.28 m if the tyres held; they do not
    old, _ = drive([(lock, 4.0)] * 8, dynamics="kinematic", speed=4.0)
    assert path_radius_and_speed(old)[0] == pytest.approx(kinematic_radius, rel=0.05)


def test_zero_to_top_speed_takes_the_drive_trains_time():
    poses, world = drive([(0.0, 4.0)] * 45)
    # the motor's force falls linearly to zero at top_speed: u(t) solves du/dt = accel (1 - u / top_speed)
    expected = SPEC.top_speed / SPEC.accel * math.log(1.0 / (1.0 - 3.6 / SPEC.top_speed))
    distance = np.linalg.norm(np.diff(np.vstack([[0, 0, 0], poses])[:, :2], axis=0), axis=1)
    reached = int(np.argmax(distance / DT > 3.6)) * DT
    assert reached == pytest.approx(expected, abs=0.2)
    assert expected > 1.0  # a 1/18 car does not reach 3.6 m/s at once ...
    assert world.drive_speed[0] == pytest.approx(4.0, abs=0.15)  # ... but gets to its command


def test_braking_takes_the_brakes_time():
    poses, world = drive([(0.0, 0.1)] * 15, speed=4.0)
    distance = np.linalg.norm(np.diff(np.vstack([[0, 0, 0], poses])[:, :2], axis=0), axis=1).sum()
    # from 4 m/s at `brake` m/s^2: about 4^2 / (2 brake) metres, not an instant stop
    assert distance == pytest.approx(4.0 ** 2 / (2 * SPEC.brake), rel=0.25)


def test_same_seed_same_race_under_the_tyre_model():
    def run():
        env = multirace.parallel_env(num_cars=2, bots=("racingline",), race="head_to_head", max_steps=150)
        env.reset(seed=7)
        rng = np.random.default_rng(3)
        while env.agents:
            env.step({a: int(rng.integers(env.action_space(a).n)) for a in env.agents})
        return env.world.poses.copy(), env.world.motion.copy()

    (poses_a, motion_a), (poses_b, motion_b) = run(), run()
    np.testing.assert_array_equal(poses_a, poses_b)
    np.testing.assert_array_equal(motion_a, motion_b)


def test_a_hard_side_hit_spins_the_car_it_hits():
    world = World(SPEC, 2, 0, 60, 15)
    world.connect()
    world.place_car(0, 0.0, 0.0, 0.0)  # at rest
    world.place_car(1, -0.08, -0.6, math.pi / 2, speed=3.0)  # driving into its side, behind its centre
    strikers = []
    for _ in range(10):
        strikers += [c.striker for c in world.step(np.array([[0.0, 0.1], [0.0, 3.0]]))]
    assert ("car", 1) in strikers and ("car", 0) not in strikers
    assert abs(world.poses[0, 2]) > math.radians(5)  # pushed round, not only sideways


def test_kinematic_model_stays_available():
    env = multirace.parallel_env(num_cars=1, dynamics="kinematic")
    assert env.world.dynamics == "kinematic"
    with pytest.raises(ValueError, match="dynamics"):
        multirace.parallel_env(num_cars=1, dynamics="magic")


def test_grip_and_motor_randomisation_reach_the_car_and_follow_the_seed():
    env = multirace.parallel_env(num_cars=2, bots=("follow@1.0",), randomize="mild")
    env.reset(seed=4)
    grip, motor = env.world.grip.copy(), env.world.motor.copy()
    assert np.all((0.9 <= grip) & (grip <= 1.05)) and np.all((0.9 <= motor) & (motor <= 1.05))
    assert len(set(grip.tolist())) == 3  # drawn per car
    env.reset(seed=4)
    np.testing.assert_array_equal(env.world.grip, grip)
    env = multirace.parallel_env(num_cars=1, randomize={"grip": (0.6, 0.6)})
    env.reset(seed=0)
    assert env.world.grip.tolist() == [0.6]
    # a car on 60 % grip holds the same steady turn at a lower speed
    world = World(SPEC, 1, 0, 60, 15)
    world.connect()
    world.grip[:] = 0.6
    world.place_car(0, 0.0, 0.0, 0.0, speed=3.0)
    poses = []
    for _ in range(60):
        world.step(np.array([[math.radians(20.0), 3.0]]))
        poses.append(world.poses[0].copy())
    radius, speed = path_radius_and_speed(np.array(poses[-16:]))
    assert speed ** 2 / radius <= 1.05 * 0.6 * SPEC.mu * GRAVITY


def test_drive_moves_each_car_as_advance_moves_it_alone():
    # nine cars: the kernel runs them four to a block, the last block part full; cars 3 and 7 are not driven
    rng = np.random.default_rng(5)
    n, rows = 9, np.array([0, 1, 2, 4, 5, 6, 8])
    params = World(SPEC, 1, 0, 60, 15)._params
    poses = np.column_stack([rng.uniform(-5, 5, n), rng.uniform(-5, 5, n), rng.uniform(-math.pi, math.pi, n)])
    motion = np.column_stack([rng.uniform(-0.1, 4.0, n), rng.normal(0, 0.3, n), rng.normal(0, 2.0, n)])
    pushes = np.column_stack([rng.normal(0, 0.2, n), rng.normal(0, 0.2, n), rng.normal(0, 1.0, n)])
    commands = np.column_stack([rng.uniform(-0.5, 0.5, n), rng.uniform(0.0, 4.0, n)])
    grip, motor = rng.uniform(0.8, 1.2, n), rng.uniform(0.8, 1.2, n)
    moved, velocity = motion.copy(), np.zeros((n, 3))
    dynamics.drive(poses, moved, velocity, rows, pushes, commands, grip, motor, params, DT)
    for i in range(n):
        if i not in rows:
            assert np.array_equal(moved[i], motion[i]) and not velocity[i].any()
            continue
        cos_y, sin_y = math.cos(poses[i, 2]), math.sin(poses[i, 2])
        push_x, push_y, push_r = pushes[i]
        u, v, r, x, y, yaw = dynamics.advance(motion[i, 0] + push_x * cos_y + push_y * sin_y,
                                              motion[i, 1] - push_x * sin_y + push_y * cos_y, motion[i, 2] + push_r,
                                              commands[i, 0], commands[i, 1], grip[i], motor[i], params, DT)
        np.testing.assert_allclose(moved[i], [u, v, r], rtol=0, atol=1e-12)
        world_step = [(x * cos_y - y * sin_y) / DT, (x * sin_y + y * cos_y) / DT, yaw / DT]
        np.testing.assert_allclose(velocity[i], world_step, rtol=0, atol=1e-12)
