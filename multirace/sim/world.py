"""The physics world: DeepRacer cars and box obstacles in one PyBullet scene.

Each car is one box body (far cheaper per physics step than the wheeled
`racecar.urdf`). Its motion comes from one of two models:

- ``dynamics="dynamic"`` (default): the single-track model with tyres and a
  drive train of `dynamics.advance`, run for all cars at once in a compiled
  kernel at its own substep; a car that enters a corner too fast slides.
- ``dynamics="kinematic"``: the kinematic bicycle of earlier versions (the
  car goes where its wheels point at any speed), for comparison and old results.

Every action step the body's velocity is set to carry it where the model
says (PyBullet commands are costly, so the car is commanded once per action
step, not once per physics step), and whatever a collision added to the
body's velocity since is fed back into the model: a hard hit can spin a car.
Contacts are real PyBullet contacts, so cars push each other and stop at
boxes; `World.step` reports who touched whom and who ran into whom.

PyBullet is stepped only in action steps where two bodies can meet
(`broadphase.may_touch`, padded wider than PyBullet's own pairing); in the
others each car moves at its velocity exactly as PyBullet moves a body that
touches nothing (to rounding, 1e-15 m a step), and PyBullet's bodies are put
in place before it is next used (`World.sync`). A time trial never steps it.
`contact_shortcut=False` steps it in every action step, as before.

The PyBullet client is created lazily (first `reset`), so a `World` pickles
and can be sent to worker processes before use.
"""
from __future__ import annotations

import itertools
import math
import os
from typing import NamedTuple

import numpy as np

from .car import CarSpec
from .broadphase import drive_cars, may_touch, move_freely
from .dynamics import DynamicsParams


def _import_pybullet():
    """Import pybullet without the "pybullet build time" banner it prints on stderr."""
    saved, devnull = os.dup(2), os.open(os.devnull, os.O_WRONLY)
    try:
        os.dup2(devnull, 2)
        import pybullet as module
    finally:
        os.dup2(saved, 2)
        os.close(saved)
        os.close(devnull)
    return module


pybullet = _import_pybullet()

CAR_COLOURS = (  # RGB, one per car slot
    (220, 40, 40), (40, 90, 230), (250, 200, 20), (30, 170, 60),
    (200, 60, 220), (255, 130, 0), (20, 200, 210), (120, 70, 30),
)
OBSTACLE_COLOUR = (250, 250, 250)
OBSTACLE_SIZE = (0.30, 0.30, 0.25)  # metres, a DeepRacer-like box (length, width, height)
PARKED_Z = -50.0  # where parked cars wait, far below the scene
SOLVER_ITERATIONS = 10
CONTACT_DISTANCE = 0.002  # metres; closer than this counts as touching
CONTACT_EVERY = 2  # physics steps between contact queries
TOUCH_PAD = 0.15  # metres around each body's bounding box where PyBullet is stepped (`broadphase.may_touch`):
# PyBullet pairs bodies some centimetres apart (contact breaking threshold, its tree's margins); in traffic
# races a pad of 0.05 m changed later contacts, 0.1 m did not (tests/test_contact_shortcut.py)
RESTING_SPEED = 0.05  # m/s; two cars that close and slide slower than this are only resting against each other
DYNAMICS = ("dynamic", "kinematic")


class Contact(NamedTuple):
    """Two bodies touched during an action step (a named tuple: a step in a bunch of cars makes several).

    `a` and `b` are ("car", i) or ("obstacle", k); `striker` is whichever of
    them drove into the other (for an obstacle, always the car). Where the two
    meet head-on more than they slide along each other (their closing speed
    along the contact normal exceeds their relative speed across it), the one
    closing faster along the normal; in a grazing contact (a car passing a
    slow one close by, or cutting in across its nose), the faster of the two,
    since a car at a crawl cannot graze anything. `striker` is None where
    neither drives into the other (closing and sliding under `RESTING_SPEED`),
    and where the striker is being pushed: a third car struck it in this action
    step or the one before (the pile-up's cause is the car that pushed it).
    """

    a: tuple[str, int]
    b: tuple[str, int]
    striker: tuple[str, int] | None


def _rgba(rgb) -> list[float]:
    return [c / 255 for c in rgb] + [1.0]


def yaw_of(quaternion) -> float:
    """Heading (rotation about z) of a quaternion (x, y, z, w)."""
    x, y, z, w = quaternion
    return math.atan2(2.0 * (w * z + x * y), 1.0 - 2.0 * (y * y + z * z))


class World:
    """PyBullet scene of `num_cars` cars and `num_obstacles` boxes."""

    def __init__(self, spec: CarSpec, num_cars: int, num_obstacles: int = 0,
                 physics_hz: int = 60, action_hz: int = 15, dynamics: str = "dynamic",
                 contact_shortcut: bool = True):
        if physics_hz % action_hz:
            raise ValueError(f"physics_hz ({physics_hz}) must be a multiple of action_hz ({action_hz})")
        if dynamics not in DYNAMICS:
            raise ValueError(f"dynamics: unknown model {dynamics!r}; choose 'dynamic' or 'kinematic'")
        self.dynamics = dynamics
        self.spec = spec
        self.num_cars = num_cars
        self.num_obstacles = num_obstacles
        self.physics_dt = 1.0 / physics_hz
        self.substeps = physics_hz // action_hz
        self.client: int | None = None
        self.car_ids: list[int] = []
        self.obstacle_ids: list[int] = []
        self._body_owner: dict[int, tuple[str, int]] = {}
        self.poses = np.zeros((num_cars, 3))  # x, y, yaw of each body centre
        self.obstacle_poses = np.zeros((num_obstacles, 3))
        self.drive_speed = np.zeros(num_cars)  # the drive train's current speed, m/s
        self.parked = np.zeros(num_cars, dtype=bool)
        self._set_velocity = np.zeros((num_cars, 3))  # last velocity we imposed: x, y, yaw rate
        self._struck_by: dict[int, set[int]] = {}  # car -> the cars that struck it in the last action step
        self.contact_shortcut = contact_shortcut
        self.action_steps = 0  # action steps taken
        self.bullet_steps = 0  # action steps PyBullet was stepped in (the others moved the cars without it)
        self._pushes_pending = False  # PyBullet was stepped since the velocities were set: its pushes count
        self._contact_pushes = np.zeros((num_cars, 3))  # what PyBullet's last step added to the set velocities
        self._no_pushes = np.zeros((num_cars, 3))  # `_pushes` where PyBullet was not stepped (read only)
        self._stale = np.zeros(num_cars, dtype=bool)  # cars moved since PyBullet's body was last put in place
        self._car_size = np.array([spec.length, spec.width])
        self._obstacle_size = np.array(OBSTACLE_SIZE[:2])
        step_time = self.physics_dt * self.substeps  # the car's command changes once per action step
        self._speed_blend = 1.0 - math.exp(-step_time / spec.speed_time_constant)
        self._grip_keep = math.exp(-step_time / spec.grip_time_constant)
        self.motion = np.zeros((num_cars, 3))  # dynamic model: (forward, left, yaw rate) in each car's frame
        self.grip = np.ones(num_cars)  # per-car scale of the tyres' friction (randomisation)
        self.motor = np.ones(num_cars)  # per-car scale of the motor's force (randomisation)
        self._params = DynamicsParams(
            mass=spec.mass, yaw_inertia=spec.yaw_inertia, front_axle=spec.wheelbase / 2,
            rear_axle=spec.wheelbase / 2, mu=spec.mu, rear_grip=spec.rear_grip, tyre_b=spec.tyre_b,
            tyre_c=spec.tyre_c, accel=spec.accel, brake=spec.brake, top_speed=spec.top_speed,
            drive_time_constant=spec.drive_time_constant,
            kinematic_speed=spec.kinematic_speed, dt=spec.dynamics_dt).as_array()

    # --------------------------------------------------------------- set-up
    def __getstate__(self):
        state = self.__dict__.copy()
        state.update(client=None, car_ids=[], obstacle_ids=[], _body_owner={})
        return state

    def connect(self) -> int:
        """Create the PyBullet DIRECT client and the bodies (once)."""
        if self.client is not None:
            return self.client
        cid = pybullet.connect(pybullet.DIRECT)
        self.client = cid
        pybullet.setGravity(0, 0, 0, physicsClientId=cid)
        pybullet.setTimeStep(self.physics_dt, physicsClientId=cid)
        # boxes sliding on a plane need far fewer solver iterations than the default 50
        pybullet.setPhysicsEngineParameter(numSolverIterations=SOLVER_ITERATIONS, physicsClientId=cid)
        s = self.spec
        car_shape = pybullet.createCollisionShape(
            pybullet.GEOM_BOX, halfExtents=[s.length / 2, s.width / 2, s.height / 2], physicsClientId=cid)
        for i in range(self.num_cars):
            look = pybullet.createVisualShape(
                pybullet.GEOM_BOX, halfExtents=[s.length / 2, s.width / 2, s.height / 2],
                rgbaColor=_rgba(CAR_COLOURS[i % len(CAR_COLOURS)]), physicsClientId=cid)
            body = pybullet.createMultiBody(s.mass, car_shape, look, [0, 3 * i, PARKED_Z], physicsClientId=cid)
            pybullet.changeDynamics(body, -1, linearDamping=0.0, angularDamping=0.0, lateralFriction=0.3,
                                    restitution=0.1, physicsClientId=cid)
            self.car_ids.append(body)
            self._body_owner[body] = ("car", i)
        lx, ly, lz = OBSTACLE_SIZE
        box_shape = pybullet.createCollisionShape(
            pybullet.GEOM_BOX, halfExtents=[lx / 2, ly / 2, lz / 2], physicsClientId=cid)
        box_look = pybullet.createVisualShape(pybullet.GEOM_BOX, halfExtents=[lx / 2, ly / 2, lz / 2],
                                              rgbaColor=_rgba(OBSTACLE_COLOUR), physicsClientId=cid)
        for k in range(self.num_obstacles):
            body = pybullet.createMultiBody(0.0, box_shape, box_look, [0, 3 * k, PARKED_Z], physicsClientId=cid)
            pybullet.changeDynamics(body, -1, lateralFriction=0.3, restitution=0.1, physicsClientId=cid)
            self.obstacle_ids.append(body)
            self._body_owner[body] = ("obstacle", k)
        return cid

    def close(self) -> None:
        """Disconnect the PyBullet client."""
        if self.client is not None:
            pybullet.disconnect(physicsClientId=self.client)
        self.client = None
        self.car_ids, self.obstacle_ids, self._body_owner = [], [], {}

    # ----------------------------------------------------------- placement
    def place_car(self, i: int, x: float, y: float, yaw: float, speed: float = 0.0) -> None:
        """Put car `i` at a pose, at rest (or rolling at `speed` along its heading)."""
        cid = self.connect()
        quat = pybullet.getQuaternionFromEuler([0, 0, yaw])
        pybullet.resetBasePositionAndOrientation(self.car_ids[i], [x, y, self.spec.height / 2], quat,
                                                 physicsClientId=cid)
        vel = (speed * math.cos(yaw), speed * math.sin(yaw), 0.0)
        pybullet.resetBaseVelocity(self.car_ids[i], [vel[0], vel[1], 0], [0, 0, 0], physicsClientId=cid)
        self._set_velocity[i] = vel
        self.drive_speed[i] = speed
        self.motion[i] = (speed, 0.0, 0.0)
        self.poses[i] = (x, y, yaw)
        self.parked[i] = False
        self._stale[i] = False
        self._contact_pushes[i] = 0.0  # put at rest: nothing pushed it
        self._struck_by.pop(i, None)  # a car put back on the track is no longer being pushed

    def park(self, i: int) -> None:
        """Take car `i` out of the scene (finished or forfeited); it no longer collides."""
        cid = self.connect()
        pybullet.resetBasePositionAndOrientation(self.car_ids[i], [0, 3 * i, PARKED_Z], [0, 0, 0, 1],
                                                 physicsClientId=cid)
        pybullet.resetBaseVelocity(self.car_ids[i], [0, 0, 0], [0, 0, 0], physicsClientId=cid)
        self._set_velocity[i] = (0.0, 0.0, 0.0)
        self.drive_speed[i] = 0.0
        self.motion[i] = 0.0
        self.parked[i] = True
        self._stale[i] = False

    def place_obstacle(self, k: int, x: float, y: float, yaw: float) -> None:
        """Put box `k` at a pose."""
        cid = self.connect()
        quat = pybullet.getQuaternionFromEuler([0, 0, yaw])
        pybullet.resetBasePositionAndOrientation(self.obstacle_ids[k], [x, y, OBSTACLE_SIZE[2] / 2], quat,
                                                 physicsClientId=cid)
        self.obstacle_poses[k] = (x, y, yaw)

    def cast_rays(self, starts: np.ndarray, ends: np.ndarray) -> np.ndarray:
        """Hit fraction (0 at the start .. 1 at the end, 1 for no hit) of each ray, rows of (M, 3) points: PyBullet's
        own ray cast, the reference the LIDAR's compiled beams (`sensors.beams`) are tested against."""
        cid = self.connect()
        self.sync()
        # one thread: each env has one core (numThreads=1 measured 15 % faster than the default here)
        hits = pybullet.rayTestBatch(starts.tolist(), ends.tolist(), numThreads=1, physicsClientId=cid)
        return np.array([hit[2] for hit in hits])

    # ------------------------------------------------------------- dynamics
    def step(self, commands: np.ndarray) -> list[Contact]:
        """Advance one action step (several physics steps) under (steer rad, speed m/s) commands.

        Each car's velocity is set once per action step to carry it where its
        motion model says. Where two bodies can touch within the step (`may_touch`),
        PyBullet integrates the physics steps and resolves the contacts within
        them; elsewhere (with `contact_shortcut`, the default) each car moves
        at its velocity as PyBullet would move a body that touches nothing, and
        PyBullet is not stepped. Returns the contacts that happened during the
        step, one per touching pair.
        """
        self.action_steps += 1
        pushes = self._pushes()
        if isinstance(commands, np.ndarray):
            commands = np.asarray(commands, np.float64)
        else:  # (steer, speed) pairs: read as one flat run (asarray takes twice the time to find their shape)
            pairs = itertools.chain.from_iterable(commands)
            commands = np.fromiter(pairs, np.float64, 2 * len(commands)).reshape(-1, 2)
        if self.dynamics == "dynamic":
            moved = self._command_dynamic(commands, pushes)
        else:
            rows = np.flatnonzero(~self.parked)
            self._command_kinematic(rows.tolist(), commands, pushes)
            moved = self.contact_shortcut and not self._may_touch(rows)
            if moved:
                self._move_freely(rows)
        if moved:
            self._struck_by = {}  # as after a step without contacts
            return []
        self.bullet_steps += 1
        self._sync_bodies()
        cid = self.client
        rows = np.flatnonzero(~self.parked)
        active = rows.tolist()
        for i, (vx, vy, turn) in zip(active, self._set_velocity[rows].tolist()):
            pybullet.resetBaseVelocity(self.car_ids[i], (vx, vy, 0.0), (0.0, 0.0, turn), cid)
        contacts: dict[tuple, Contact] = {}
        for substep in range(self.substeps):
            pybullet.stepSimulation(cid)
            if substep % CONTACT_EVERY == CONTACT_EVERY - 1 or substep == self.substeps - 1:
                self._collect_contacts(contacts)
        self._read_bodies(active)
        self._pushes_pending = True
        return self._clear_pushed_strikers(list(contacts.values()))

    def _pushes(self) -> np.ndarray:
        """What PyBullet's last step added to each car's velocity (rows of x, y, yaw rate, world frame; a parked
        car's row is not read): the contacts' pushes (`_read_bodies`; zero for a car put somewhere since). Zero
        where PyBullet was not stepped since the velocities were last set (`_no_pushes`)."""
        if not self._pushes_pending:
            return self._no_pushes
        self._pushes_pending = False
        return self._contact_pushes

    def _may_touch(self, rows: np.ndarray) -> bool:
        """Whether any two bodies' padded bounding boxes can overlap during the step, moving at their set
        velocities (a conservative broad phase: it never misses a pair PyBullet would make)."""
        poses, velocity = self.poses, self._set_velocity
        if len(rows) < self.num_cars:  # some cars parked: only the others (with none, no copies)
            poses, velocity = poses[rows], velocity[rows]
        return may_touch(poses, velocity, self.obstacle_poses, self._car_size, self._obstacle_size,
                         self.physics_dt * self.substeps, TOUCH_PAD)

    def _move_freely(self, rows: np.ndarray) -> None:
        """Move these cars as PyBullet moves a body that touches nothing (`broadphase.move_freely`)."""
        move_freely(self.poses, self._set_velocity, rows, self.substeps, self.physics_dt)
        self._stale[rows] = True

    def sync(self) -> None:
        """Bring PyBullet's bodies to the cars' poses (after steps that moved the cars without PyBullet):
        call before anything reads the scene from PyBullet (rays, its camera)."""
        if self._stale.any():
            self._sync_bodies()

    def _sync_bodies(self) -> None:
        cid, height = self.client, self.spec.height / 2
        for i in np.flatnonzero(self._stale).tolist():
            x, y, yaw = self.poses[i].tolist()
            pybullet.resetBasePositionAndOrientation(self.car_ids[i], (x, y, height),
                                                     (0.0, 0.0, math.sin(yaw / 2), math.cos(yaw / 2)), cid)
        self._stale[:] = False

    def _clear_pushed_strikers(self, contacts: list[Contact]) -> list[Contact]:
        """The step's contacts with no striker where the striker was being pushed by a third car (struck by it
        in this step or the last one); remembers who struck whom for the next step."""
        hits = [(k, c.striker[1], (c.b if c.striker == c.a else c.a)[1]) for k, c in enumerate(contacts)
                if c.a[0] == c.b[0] == "car" and c.striker is not None]  # (index, striker car, struck car)
        struck_by: dict[int, set[int]] = {}
        for _, striker, struck in hits:
            struck_by.setdefault(struck, set()).add(striker)
        for k, striker, struck in hits:
            if (struck_by.get(striker, set()) | self._struck_by.get(striker, set())) - {struck}:
                contacts[k] = contacts[k]._replace(striker=None)
        self._struck_by = struck_by
        return contacts

    def _command_dynamic(self, commands: np.ndarray, pushes: np.ndarray) -> bool:
        """Run the tyre model for the cars not parked (a push since the last step joins their motion), set the
        velocities that carry them where it says and, with `contact_shortcut`, move them there if no two
        bodies can touch within the step, all in one compiled call (`broadphase.drive_cars`). Returns whether
        it moved them (if not, PyBullet must)."""
        return drive_cars(self.poses, self.motion, self._set_velocity, self.drive_speed, self.parked, self._stale,
                          pushes, commands, self.grip, self.motor, self._params, self.obstacle_poses,
                          self._car_size, self._obstacle_size, self.substeps, self.physics_dt, TOUCH_PAD,
                          self.contact_shortcut)

    def _command_kinematic(self, active: list[int], commands, pushes) -> None:
        """The kinematic bicycle: the velocity points along the heading the car will have half-way
        through the step (the midpoint rule, so arcs are followed closely), with the yaw rate held."""
        step_time = self.physics_dt * self.substeps
        commands = [(float(steer), float(speed)) for steer, speed in commands]  # plain floats: fast maths
        yaws, drive_speed = self.poses[:, 2].tolist(), self.drive_speed.tolist()
        pushes = pushes.tolist()
        for i in active:
            # what a collision (or anything but our own command) changed since we set the velocity
            push_x, push_y, _ = pushes[i]
            yaw = yaws[i]
            cos_y, sin_y = math.cos(yaw), math.sin(yaw)
            steer, target = commands[i]
            speed = drive_speed[i] + push_x * cos_y + push_y * sin_y
            speed += (target - speed) * self._speed_blend
            self.drive_speed[i] = speed
            tan_steer = math.tan(steer)
            beta = math.atan(0.5 * tan_steer)
            yaw_rate = speed * math.cos(beta) * tan_steer / self.spec.wheelbase
            direction = yaw + 0.5 * yaw_rate * step_time + beta
            # the sideways part of a push decays with the tyres' grip
            side = (-push_x * sin_y + push_y * cos_y) * self._grip_keep
            self._set_velocity[i] = (speed * math.cos(direction) - side * sin_y,
                                     speed * math.sin(direction) + side * cos_y, yaw_rate)

    def _collect_contacts(self, contacts: dict) -> None:
        planar = None  # every car's (x, y) velocity set for the step, read once if a new pair touches
        for point in pybullet.getContactPoints(physicsClientId=self.client):
            if point[8] > CONTACT_DISTANCE:
                continue
            body_a, body_b = point[1], point[2]
            key = (body_a, body_b) if body_a < body_b else (body_b, body_a)
            if key in contacts:
                continue
            a = self._body_owner.get(body_a)
            b = self._body_owner.get(body_b)
            if a is None or b is None or (a[0] == "obstacle" and b[0] == "obstacle"):
                continue
            normal_on_b = point[7]  # points from B towards A
            if planar is None:
                planar = self._set_velocity[:, :2].tolist()
            ax, ay = planar[a[1]] if a[0] == "car" else (0.0, 0.0)  # a box is at rest
            bx, by = planar[b[1]] if b[0] == "car" else (0.0, 0.0)
            approach_a = -(ax * normal_on_b[0] + ay * normal_on_b[1])  # A's speed towards B
            approach_b = bx * normal_on_b[0] + by * normal_on_b[1]  # B's speed towards A
            closing = approach_a + approach_b
            sliding = abs((ax - bx) * normal_on_b[1] - (ay - by) * normal_on_b[0])  # relative speed across n
            if a[0] == "obstacle" or b[0] == "obstacle":
                striker = a if a[0] == "car" else b
            elif max(closing, sliding) <= RESTING_SPEED:  # neither drives into the other (a push made it)
                striker = None
            elif closing > sliding:  # a hit: the one closing faster along the normal struck
                striker = a if approach_a >= approach_b else b
            else:  # a graze: the faster car ran along the other
                striker = a if math.hypot(ax, ay) >= math.hypot(bx, by) else b
            first, second = (a, b) if a <= b else (b, a)
            contacts[key] = Contact(a=first, b=second, striker=striker)

    def _read_bodies(self, active: list[int]) -> None:
        """After PyBullet's step: the `active` cars' poses, and what the step added to the velocities set for
        it (their rows of `_contact_pushes`)."""
        cid, height = self.client, self.spec.height / 2
        poses, velocities = [], []
        for i in active:
            body = self.car_ids[i]
            pos, orn = pybullet.getBasePositionAndOrientation(body, cid)
            yaw = yaw_of(orn)
            # contacts at box edges can tip a body a little: put it back flat
            if abs(orn[0]) > 1e-3 or abs(orn[1]) > 1e-3 or abs(pos[2] - height) > 1e-3:
                flat = pybullet.getQuaternionFromEuler([0, 0, yaw])
                pybullet.resetBasePositionAndOrientation(body, [pos[0], pos[1], height], flat, cid)
            poses.append((pos[0], pos[1], yaw))
            (vx, vy, _), (_, _, turn) = pybullet.getBaseVelocity(body, cid)
            velocities.append((vx, vy, turn))
        if poses:
            self.poses[active] = poses
            self._contact_pushes[active] = np.array(velocities) - self._set_velocity[active]
