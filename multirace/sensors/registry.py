"""The sensor registry: every sensor a car can carry, by its model_metadata name (`sensor.Sensor`).

Adding a sensor is one file (a `Sensor` subclass with its name, observation
key, `space` and `observe`) plus one line in `SENSORS` below; the env, the
agent networks, agent files, export/import and training read it from here.
"""
from __future__ import annotations

from .camera_sensors import FrontCamera, StereoCameras, TwoFrameCamera
from .lidar_sensors import LidarSensor, SectorLidar
from .sensor import Sensor
from .speed import Speed

SENSORS: tuple[Sensor, ...] = (
    FrontCamera(),
    StereoCameras(),
    TwoFrameCamera(),
    LidarSensor(),
    SectorLidar(),
    Speed(),
)
BY_NAME = {name: sensor for sensor in SENSORS for name in (sensor.name, *sensor.aliases)}
BY_KIND = {sensor.kind: sensor for sensor in SENSORS}
CAMERA_KEY = "camera"  # the key every car fills: its camera image


def sensor_named(name: str, where: str = "sensor") -> Sensor:
    """The registry's sensor called `name`; ValueError naming `where` and the known names otherwise."""
    try:
        return BY_NAME[name]
    except (KeyError, TypeError):
        deepracer = ", ".join(n for n, s in BY_NAME.items() if s.on_deepracer)
        ours = ", ".join(n for n, s in BY_NAME.items() if not s.on_deepracer)
        raise ValueError(f"{where}: unknown sensor {name!r}; DeepRacer's sensors are {deepracer} "
                         f"(and multirace's own {ours})") from None
