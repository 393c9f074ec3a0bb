"""Which sensors a car carries, named as DeepRacer's model_metadata names them (`registry` holds them all).

DeepRacer's ``sensor`` list combines one camera and at most one range sensor:

- cameras: ``FRONT_FACING_CAMERA`` (one grey camera; ``observation`` and
  ``LEFT_CAMERA`` are DeepRacer's older names for a single camera) or
  ``STEREO_CAMERAS`` (two grey cameras side by side: a 2-channel image,
  [left, right]);
- range sensors: ``LIDAR`` (64 ranges over 300 degrees) or ``SECTOR_LIDAR``
  (8 binary sectors of the same scan: 1.0 where something is nearer than
  0.5 m).

multirace adds sensors DeepRacer's cars do not have, for research: ``SPEED``
(the car's own drive speed) and ``FRONT_FACING_CAMERA_TWO_FRAMES`` (the single
grey camera's image and the one a step before it, a 2-channel image [now,
before]: how fast things move, which one frame cannot show). A car carries
one sensor per observation key (one camera, at most one LIDAR, ...). An
unknown name is an error, never silently dropped.

A suite's observation is the camera image alone, or with any other sensor a
dict {key: value} (``{"camera": image, "lidar": ranges, "speed": [m/s]}``).
"""
from __future__ import annotations

import dataclasses
import functools

from gymnasium import spaces

from .camera import CameraSpec
from .registry import BY_KIND, CAMERA_KEY, SENSORS, sensor_named
from .sensor import Sensor, SensorView


@dataclasses.dataclass(frozen=True)
class SensorSuite:
    """A car's sensors: its camera ("mono", "stereo" or "frames"), its range sensor (None, "lidar" or "sector")
    and the kinds of its other sensors (e.g. ("speed",)), each a `registry` entry."""

    camera: str = "mono"
    lidar: str | None = None
    extras: tuple[str, ...] = ()

    @functools.cached_property  # read at every observation
    def entries(self) -> tuple[Sensor, ...]:
        """Its registry entries in observation order: the camera, the range sensor, the others."""
        kinds = (self.camera, self.lidar, *self.extras)
        return tuple(BY_KIND[kind] for kind in kinds if kind is not None)

    def __reduce__(self):
        """Pickled as its fields alone: unpickled, its `entries` are the registry's own again, not copies."""
        return SensorSuite, (self.camera, self.lidar, self.extras)

    @property
    def names(self) -> list[str]:
        """The DeepRacer `sensor` list for these sensors."""
        return [sensor.name for sensor in self.entries]

    @property
    def range_inputs(self) -> int:
        """Values the range sensor gives per step: 64 ranges (LIDAR), 8 sectors (SECTOR_LIDAR) or 0 (none)."""
        return self.vector_inputs.get("lidar", 0)

    @property
    def vectors(self) -> tuple[Sensor, ...]:
        """The sensors beside the camera, each giving a float32 vector."""
        return self.entries[1:]

    @property
    def vector_inputs(self) -> dict[str, int]:
        """{observation key: float32 values per step} of the sensors beside the camera (a net's extra inputs)."""
        return {sensor.key: sensor.inputs for sensor in self.vectors}

    @property
    def on_deepracer(self) -> bool:
        """Whether DeepRacer's cars carry every one of these sensors."""
        return all(sensor.on_deepracer for sensor in self.entries)

    def space(self, camera: CameraSpec) -> spaces.Space:
        """The observation space: the camera's images alone, else a Dict of every sensor's space by key."""
        if not self.vectors:
            return self.entries[0].space(camera)
        return spaces.Dict({sensor.key: sensor.space(camera) for sensor in self.entries})

    def observe(self, view: SensorView, agents: list[str]) -> dict:
        """{agent: observation} for the view's cars (the agents, in order): sensors observed in suite order."""
        readings = [(sensor.key, sensor.observe(view)) for sensor in self.entries]
        if len(readings) == 1:
            return dict(zip(agents, readings[0][1]))
        return {agent: {key: values[k] for key, values in readings} for k, agent in enumerate(agents)}


def suite_of(sensors, where: str = "sensor", names=None) -> SensorSuite:
    """The suite of these registry entries; ValueError naming `where` unless one camera and one sensor per key."""
    keys = [sensor.key for sensor in sensors]
    if len(set(keys)) != len(keys):
        raise ValueError(f"{where}: {names!r} names more than one camera or more than one LIDAR; a car carries one "
                         "sensor per kind: one camera (FRONT_FACING_CAMERA, STEREO_CAMERAS or "
                         "FRONT_FACING_CAMERA_TWO_FRAMES), at most one of "
                         "LIDAR, SECTOR_LIDAR")
    by_key = {sensor.key: sensor for sensor in sensors}
    if CAMERA_KEY not in by_key:
        raise ValueError(f"{where}: {names!r} has no camera; add FRONT_FACING_CAMERA or STEREO_CAMERAS")
    lidar = by_key.get("lidar")
    extras = tuple(s.kind for s in SENSORS if s in sensors and s.key not in (CAMERA_KEY, "lidar"))
    return SensorSuite(by_key[CAMERA_KEY].kind, lidar.kind if lidar else None, extras)


def parse_sensors(names, where: str = "sensor") -> SensorSuite:
    """The suite a DeepRacer `sensor` list asks for; ValueError naming `where` for anything else."""
    if isinstance(names, str):
        names = [names]
    if not isinstance(names, (list, tuple)) or not names or not all(isinstance(n, str) for n in names):
        raise ValueError(f"{where}: expected a non-empty list of sensor names such as [\"FRONT_FACING_CAMERA\"], "
                         f"got {names!r}")
    return suite_of([sensor_named(name, where) for name in names], where, names)


def declared_sensors(sensor=None, lidar: bool = False, where: str = "sensor") -> SensorSuite:
    """The suite of a `sensor` list (None: the single camera); `lidar=True` is the shorthand that adds the
    64-beam LIDAR to a list that names no range sensor."""
    suite = parse_sensors(sensor, where) if sensor is not None else SensorSuite()
    return dataclasses.replace(suite, lidar="lidar") if lidar and suite.lidar is None else suite


def race_suite(suites) -> SensorSuite:
    """What a race's env must provide so that every entrant gets its sensors: per observation key, the sensor
    whose values every entrant's sensor of that key reads (`Sensor.covers`): a stereo pair if anyone reads one
    (single-camera entrants see its left camera), the full LIDAR scan if anyone reads a LIDAR (sector entrants
    reduce it to sectors), and every other sensor anyone reads."""
    wanted: dict[str, set] = {}
    for suite in suites:
        for sensor in suite.entries:
            wanted.setdefault(sensor.key, set()).add(sensor)
    chosen = [_covering(group) for group in wanted.values()]
    return suite_of(chosen) if chosen else SensorSuite()


def _covering(sensors: set) -> Sensor:
    """The one of `sensors` (all of one key) whose values the others read."""
    for sensor in sensors:
        if all(other is sensor or other.name in sensor.covers for other in sensors):
            return sensor
    raise ValueError(f"no sensor gives what {sorted(s.name for s in sensors)} all read; race them apart")
