"""Privileged state of a race: what a car would know with perfect sensing, as flat float32 vectors.

Two views of the same step, read from the env's published `RaceState` (``env.race_state``):

- `car_features(env, i)`: car i's own view (ego-centric), the observation of
  ``observation="state"`` envs and of the RL teachers that learn from it
  ("learning by cheating": a state policy learns to race fast, with no camera
  to render and no CNN to train, then teaches a camera policy by DAgger).
  Its speed over the ground, slip and yaw rate, the command it is carrying
  out, where it sits on the road, the centre line ahead of it in its own frame
  (which holds the heading error and the curvature to come), and the cars
  ahead and behind most in its way (the nearest along the track, a car that
  sits clear to one side counting as farther: `in_the_way`). A DeepRacer car
  measures none of these; the camera policies that ship read only their
  sensors. With ``view="camera"`` the cars it lists are only those its
  front camera shows (`in_camera_view`): a teacher that knows no more of
  the traffic than a camera student can see, so that what it does, the
  student can learn (a car being passed, alongside, is out of both views).
- `global_state(env)`: every car's pose, motion, race distance, position on
  the road and the curvature ahead of it, for centralised critics
  (PettingZoo's `state()`).
"""
from __future__ import annotations

import math

import numpy as np

LOOKAHEAD = np.array([0.25, 0.5, 0.75, 1.0, 1.5, 2.0, 2.5, 3.0, 4.0, 5.0])  # metres along the centre line
TRAFFIC_AHEAD, TRAFFIC_BEHIND = 2, 1  # cars ahead and behind in the ego view (those most in its way)
TRAFFIC_RANGE = 5.0  # metres; cars farther along the track than this are not in the ego view
SIDE_WEIGHT = 2.0  # a car ahead or behind counts this many metres farther per metre it sits clear to one side
MAX_SPEED = 4.0  # m/s: speeds are scaled by this
CURVATURE_AHEAD = (1.0, 2.0, 3.0)  # metres: the global state's heading change of the centre line to these points
STATE_BOUND = 1e4  # every state value lies within +-this (the spaces' bounds)
STATE_VIEWS = ("all", "camera")  # the traffic in the ego view: every car near, or those the front camera shows
OUTLINE = ((1, 1), (1, 0), (1, -1), (0, 1), (0, -1), (-1, 1), (-1, 0), (-1, -1))  # a body's outline points
# that `in_camera_view` tries, in half-lengths along the body and half-widths aside
CAR_FEATURES = 11 + 2 * len(LOOKAHEAD) + 4 * (TRAFFIC_AHEAD + TRAFFIC_BEHIND)
GLOBAL_PER_CAR = 13 + len(CURVATURE_AHEAD)


def centre_points(track, s: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Centre-line (x, y, heading) at the arc lengths `s` (any shape, wrapped round the loop)."""
    s = np.mod(s, track.length)
    i = np.clip(np.searchsorted(track.cum_s, s, side="right") - 1, 0, len(track.seg_len) - 1)
    t = (s - track.cum_s[i]) / np.maximum(track.seg_len[i], 1e-9)
    xy = track.seg_start[i] + t[..., None] * track.seg_vec[i]
    return xy[..., 0], xy[..., 1], track.seg_heading[i]


def _wrap(angle):
    return (angle + math.pi) % (2 * math.pi) - math.pi


def _motion(env, i: int) -> tuple[float, float, float]:
    """(forward speed, leftward speed, yaw rate) of car i; the kinematic car has no slip."""
    world = env.world
    if world.dynamics == "dynamic":
        forward, left, yaw_rate = (float(v) for v in world.motion[i])
        return forward, left, yaw_rate
    return float(world.drive_speed[i]), 0.0, 0.0


def in_the_way(gap: float, lateral: float, car_width: float) -> float:
    """How much in the way a car `gap` metres ahead (or behind) and `lateral` metres aside is, as a distance:
    the gap, plus `SIDE_WEIGHT` times how far it sits beyond a car's width to the side (0 where the two would
    touch if one caught the other). In a pack, the car in line 0.45 m ahead comes before one alongside 0.5 m
    to the side."""
    return gap + SIDE_WEIGHT * max(0.0, abs(lateral) - car_width)


def in_camera_view(camera, me, other, spec) -> bool:
    """Whether car `other` shows in car `me`'s front camera (`camera`, a `CameraSpec`): some point of its body
    outline (corners and edge midpoints) ahead of the lens and within the horizontal field of view. Other cars
    in front of it are not taken to hide it."""
    cos, sin = math.cos(me.yaw), math.sin(me.yaw)
    lens_x, lens_y = me.x + camera.forward * cos, me.y + camera.forward * sin
    tan_half = math.tan(camera.hfov / 2)
    other_cos, other_sin = math.cos(other.yaw), math.sin(other.yaw)
    half_length, half_width = spec.length / 2, spec.width / 2
    for along, aside in OUTLINE:
        ox, oy = along * half_length, aside * half_width
        dx = other.x + ox * other_cos - oy * other_sin - lens_x
        dy = other.y + ox * other_sin + oy * other_cos - lens_y
        forward = dx * cos + dy * sin
        if forward > 0 and abs(dy * cos - dx * sin) < forward * tan_half:
            return True
    return False


def _near(state, i: int, camera=None, shown_by=None) -> tuple[list, list]:
    """The cars within `TRAFFIC_RANGE` ahead of car i and those behind it, each most in the way first
    (`in_the_way`), as (gap, lateral difference, speed, shown) rows; with `camera` (a `CameraSpec`), only the
    cars car i's camera shows. `shown` says whether the camera `shown_by` shows the car (False without one)."""
    ahead, behind = [], []
    length, width = state.track.length, state.car_spec.width
    me = state.cars[i]
    others = [car for car in state.cars if car.located and car.index != i]  # `traffic`'s cars, in its order
    for (along, lateral, speed), car in zip(state.traffic(i), others):
        if camera is not None and not in_camera_view(camera, me, car, state.car_spec):
            continue
        shown = shown_by is not None and in_camera_view(shown_by, me, car, state.car_spec)
        if along <= TRAFFIC_RANGE:
            ahead.append((in_the_way(along, lateral, width), along, lateral, speed, shown))
        elif length - along <= TRAFFIC_RANGE:
            behind.append((in_the_way(length - along, lateral, width), length - along, lateral, speed, shown))
    return [car[1:] for car in sorted(ahead)], [car[1:] for car in sorted(behind)]


def _traffic_features(state, i: int, camera=None) -> list[float]:
    """(present, gap / range, lateral difference, speed difference / max) of the cars ahead, then behind, most
    in the way first (`in_the_way`); with `camera` (a `CameraSpec`), only the cars car i's camera shows."""
    own = state.cars[i].speed
    rows = []
    for cars, count in zip(_near(state, i, camera), (TRAFFIC_AHEAD, TRAFFIC_BEHIND)):
        for k in range(count):
            if k < len(cars):
                gap, lateral, speed, _ = cars[k]
                rows += [1.0, gap / TRAFFIC_RANGE, lateral, (speed - own) / MAX_SPEED]
            else:
                rows += [0.0, 1.0, 0.0, 0.0]
    return rows


def ahead_in_camera(env, i: int) -> list[bool]:
    """For each of the `TRAFFIC_AHEAD` rows ahead of `car_features(env, i)` (view "all"): whether car i's front
    camera shows that car (False for an empty row)."""
    ahead, _ = _near(env.race_state, i, shown_by=env.camera)
    return [k < len(ahead) and ahead[k][3] for k in range(TRAFFIC_AHEAD)]


def slowed_ahead(features: np.ndarray, speed: float, only=None) -> np.ndarray:
    """`car_features` rows (N, CAR_FEATURES) with every car they list ahead taken to drive at `speed` m/s where
    it drives faster: the worst case that what a camera frame shows (where a car is, not how fast it goes)
    cannot rule out. `only` (N, TRAFFIC_AHEAD) bools: slow only the rows ahead marked (e.g. the cars a camera
    shows, `ahead_in_camera`). A copy; the cars behind are left as they are."""
    out = np.array(features, np.float32)
    assumed = float(speed) / MAX_SPEED - out[:, 3]  # (the ego speed is the fourth value, over MAX_SPEED)
    first = CAR_FEATURES - 4 * (TRAFFIC_AHEAD + TRAFFIC_BEHIND)  # the first traffic row
    marked = np.ones((len(out), TRAFFIC_AHEAD), bool) if only is None else np.asarray(only, bool)
    for k in range(TRAFFIC_AHEAD):
        present, closing = out[:, first + 4 * k], out[:, first + 4 * k + 3]
        out[:, first + 4 * k + 3] = np.where((present > 0) & marked[:, k], np.minimum(closing, assumed), closing)
    return out


def car_features(env, i: int, view: str = "all") -> np.ndarray:
    """Car i's privileged ego view (`CAR_FEATURES` float32 values; see the module docstring); `view`
    ("all" or "camera", `STATE_VIEWS`): which of the cars near it that view lists."""
    state = env.race_state
    car = state.cars[i]
    if not car.located:  # a parked car: nothing to see
        return np.zeros(CAR_FEATURES, np.float32)
    x, y, yaw = car.x, car.y, car.yaw
    forward, left, yaw_rate = _motion(env, i)
    steer, speed = car.command
    half = max(car.track_width / 2, 1e-3)
    error = _wrap(yaw - car.track_heading)
    px, py, _ = centre_points(state.track, car.s + LOOKAHEAD)
    dx, dy = px - x, py - y
    cos, sin = math.cos(yaw), math.sin(yaw)
    ahead_x, ahead_y = cos * dx + sin * dy, -sin * dx + cos * dy  # the centre line in the car's frame
    values = [forward / MAX_SPEED, left, yaw_rate / 3.0, car.speed / MAX_SPEED,
              steer / env.car_spec.max_steer, speed / MAX_SPEED, car.lateral / half, car.left_width,
              car.right_width, math.sin(error), math.cos(error)]
    camera = env.camera if view == "camera" else None
    values += (ahead_x / LOOKAHEAD).tolist() + (ahead_y / LOOKAHEAD).tolist() + _traffic_features(state, i, camera)
    return np.clip(np.asarray(values, np.float32), -STATE_BOUND, STATE_BOUND)


def global_state(env) -> np.ndarray:
    """Every car's state, learning cars then bots (`GLOBAL_PER_CAR` values each; see the module docstring)."""
    track = env.track
    rows = np.zeros((env.total_cars, GLOBAL_PER_CAR), np.float32)
    centre = (track.bounds[0] + track.bounds[1]) / 2
    cars = env.race_state.cars if env.race_state is not None else ()
    for car in cars:
        if not car.located:
            continue
        i, race, yaw = car.index, car.race, car.yaw
        forward, left, yaw_rate = _motion(env, i)
        _, _, headings = centre_points(track, car.s + np.array(CURVATURE_AHEAD))
        rows[i] = [1.0, (car.x - centre[0]) / 10.0, (car.y - centre[1]) / 10.0, math.cos(yaw), math.sin(yaw),
                   forward / MAX_SPEED, left, yaw_rate / 3.0, race.distance / track.length, race.laps,
                   car.lateral / max(car.track_width / 2, 1e-3), math.sin(_wrap(yaw - car.track_heading)),
                   math.cos(_wrap(yaw - car.track_heading)), *(_wrap(headings - car.track_heading))]
    return np.clip(rows.reshape(-1), -STATE_BOUND, STATE_BOUND)
