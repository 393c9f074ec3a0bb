"""DeepRacer's range sensors as sensors: ``LIDAR`` (64 ranges, `lidar`) and ``SECTOR_LIDAR`` (8 binary sectors).

Both fill the observation key ``lidar`` with float32 vectors; their noise
comes from the env's sensor noise stream (`SensorView.noise`).
"""
from __future__ import annotations

import functools

import numpy as np

from ..sim.car import CarSpec
from .lidar import SECTORS, Lidar, LidarSpec, sector_lidar
from .sensor import SensorView, VectorSensor


@functools.lru_cache(maxsize=None)
def scanner(car_spec: CarSpec) -> Lidar:
    """The 64-beam scanner of a car of `car_spec` (one per spec: its beam geometry is computed once)."""
    return Lidar(car_spec)


class LidarSensor(VectorSensor):
    """DeepRacer's LIDAR: 64 ranges in metres, clipped to 0.15 .. 1.0 (no echo reads 1.0)."""

    name, key, kind, unit = "LIDAR", "lidar", "lidar", "LIDAR ranges"
    inputs, low, high, empty = LidarSpec().samples, LidarSpec().min_range, LidarSpec().max_range, LidarSpec().max_range
    covers = ("SECTOR_LIDAR",)  # a SECTOR_LIDAR car reduces the scan to its sectors

    def observe(self, view: SensorView) -> np.ndarray:
        return scanner(view.car_spec).scan(view.world, view.cars, view.noise)


class SectorLidar(VectorSensor):
    """DeepRacer's SECTOR_LIDAR: the scan in 8 sectors, 1.0 where something is nearer than 0.5 m, else 0.0."""

    name, key, kind, unit = "SECTOR_LIDAR", "lidar", "sector", "SECTOR_LIDAR sectors"
    inputs = SECTORS

    def observe(self, view: SensorView) -> np.ndarray:
        return sector_lidar(scanner(view.car_spec).scan(view.world, view.cars, view.noise))

    def reads(self, value):
        value = np.asarray(value, np.float32)
        return sector_lidar(value) if value.shape == (LidarSensor.inputs,) else value
