"""Which sensors a car carries, named as DeepRacer's model_metadata names them.

DeepRacer's ``sensor`` list combines one camera and at most one range sensor:

- cameras: ``FRONT_FACING_CAMERA`` (one grey camera; ``observation`` and
  ``LEFT_CAMERA`` are DeepRacer's older names for a single camera) or
  ``STEREO_CAMERAS`` (two grey cameras side by side: a 2-channel image,
  [left, right]);
- range sensors: ``LIDAR`` (64 ranges over 300 degrees) or ``SECTOR_LIDAR``
  (8 binary sectors of the same scan: 1.0 where something is nearer than
  0.5 m).

An unknown name is an error, never silently dropped.
"""
from __future__ import annotations

import dataclasses

from .lidar import SECTORS, LidarSpec

CAMERAS = {"FRONT_FACING_CAMERA": "mono", "observation": "mono", "LEFT_CAMERA": "mono", "STEREO_CAMERAS": "stereo"}
RANGE_SENSORS = {"LIDAR": "lidar", "SECTOR_LIDAR": "sector"}
KNOWN = (*CAMERAS, *RANGE_SENSORS)
RANGE_INPUTS = {"lidar": LidarSpec().samples, "sector": SECTORS}  # values a range sensor gives per step


@dataclasses.dataclass(frozen=True)
class SensorSuite:
    """A car's sensors: its camera ("mono" or "stereo") and its range sensor (None, "lidar" or "sector")."""

    camera: str = "mono"
    lidar: str | None = None

    @property
    def names(self) -> list[str]:
        """The DeepRacer `sensor` list for these sensors."""
        names = ["STEREO_CAMERAS" if self.camera == "stereo" else "FRONT_FACING_CAMERA"]
        if self.lidar is not None:
            names.append("LIDAR" if self.lidar == "lidar" else "SECTOR_LIDAR")
        return names

    @property
    def camera_channels(self) -> int | None:
        """Channels the camera image must have (2 for stereo; None: 1 or 3, grey or colour)."""
        return 2 if self.camera == "stereo" else None

    @property
    def range_inputs(self) -> int:
        """Values the range sensor gives per step: 64 ranges (LIDAR), 8 sectors (SECTOR_LIDAR) or 0 (none)."""
        return RANGE_INPUTS.get(self.lidar, 0)


def parse_sensors(names, where: str = "sensor") -> SensorSuite:
    """The suite a DeepRacer `sensor` list asks for; ValueError naming `where` for anything else."""
    if isinstance(names, str):
        names = [names]
    if not isinstance(names, (list, tuple)) or not names or not all(isinstance(n, str) for n in names):
        raise ValueError(f"{where}: expected a non-empty list of sensor names such as [\"FRONT_FACING_CAMERA\"], "
                         f"got {names!r}")
    unknown = [n for n in names if n not in KNOWN]
    if unknown:
        raise ValueError(f"{where}: unknown sensor {unknown[0]!r}; DeepRacer's sensors are {', '.join(KNOWN)}")
    cameras = [CAMERAS[n] for n in names if n in CAMERAS]
    ranges = [RANGE_SENSORS[n] for n in names if n in RANGE_SENSORS]
    if len(cameras) > 1 or len(ranges) > 1:
        raise ValueError(f"{where}: {names!r} names more than one camera or more than one LIDAR; a car carries one "
                         "camera (FRONT_FACING_CAMERA or STEREO_CAMERAS) and at most one of LIDAR, SECTOR_LIDAR")
    if not cameras:
        raise ValueError(f"{where}: {names!r} has no camera; add FRONT_FACING_CAMERA or STEREO_CAMERAS")
    return SensorSuite(camera=cameras[0], lidar=ranges[0] if ranges else None)


def declared_sensors(sensor=None, lidar: bool = False, where: str = "sensor") -> SensorSuite:
    """The suite of a `sensor` list (None: the single camera); `lidar=True` is the shorthand that adds the
    64-beam LIDAR to a list that names no range sensor."""
    suite = parse_sensors(sensor, where) if sensor is not None else SensorSuite()
    return dataclasses.replace(suite, lidar="lidar") if lidar and suite.lidar is None else suite


def race_suite(suites) -> SensorSuite:
    """What a race's env must provide so that every entrant gets its sensors: a stereo pair if anyone
    reads one (single-camera entrants see its left camera), the full LIDAR scan if anyone reads a LIDAR
    (sector entrants reduce it to sectors)."""
    suites = list(suites)
    camera = "stereo" if any(s.camera == "stereo" for s in suites) else "mono"
    kinds = {s.lidar for s in suites} - {None}
    lidar = None if not kinds else (kinds.pop() if len(kinds) == 1 else "lidar")
    return SensorSuite(camera=camera, lidar=lidar)
