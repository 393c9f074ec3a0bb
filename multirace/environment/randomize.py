"""Seeded domain randomisation of perception and dynamics (off by default).

API (for wiring into `env.py`)
------------------------------
``Randomization.from_config(config) -> Randomization``
    `config` is the env's ``randomize=`` keyword: ``None`` (everything off,
    same as ``"none"``), a preset name (``"none"``, ``"mild"``, ``"strong"``),
    or a dict of field overrides, optionally with a ``"preset"`` key naming
    the base (default ``"none"``), e.g. ``{"preset": "mild", "noise_sigma":
    (0, 6)}``. Raises ``ValueError`` naming the unknown key, preset or the bad
    range. ``Randomization.preset(name)`` gives a preset directly.
``Randomization.enabled`` / ``.perception_enabled`` / ``.dynamics_enabled``
    False when the corresponding part is the identity: the env can skip
    `apply_image` / `apply_command` and keep its own code path unchanged.
``Randomization.draw_episode(rng, num_cars=1) -> EpisodeDraw``
    Call once per ``reset`` (after seeding). Fixes for the episode: the scene
    `palette` (rebuild ``TrackTexture(track, draw.palette)`` and the renderer
    when ``draw.palette != texture.palette``; building a texture is costly),
    `camera_jitter[i]` per car (pass to ``camera_pose(spec, pose,
    jitter=draw.camera_jitter[i])``), the lighting (brightness, contrast, hue,
    saturation), noise level, blur kernel, shadow shapes, and per-car dynamics
    (steering offset, speed gain, noise multipliers).
``apply_image(image, rng, draw) -> image``
    Per camera frame: uint8 (H, W, 1) or (H, W, 3) in, a new uint8 array of
    the same shape out. Order: shadows, blur, lighting (brightness, contrast,
    hue, saturation), sensor noise. Consumes exactly one ``rng.random(5)``
    per call whatever is enabled, so streams stay aligned. The noise field
    and shadow masks are made once per episode and image shape, so each
    frame only crops/selects them (`multirace bench` measures the cost).
``apply_command(steer_deg, speed, draw, rng, car=0, spec=None) -> (steer_deg, speed)``
    Per car per step, on the commanded action before ``spec.clamp_command``:
    adds the steering offset, multiplies by the speed gain, and adds
    DeepRacer's Gaussian action noise (``spec.steer_noise`` rad,
    ``spec.speed_noise`` m/s, from ``CarSpec()`` if `spec` is None) scaled by
    the car's drawn multipliers. It REPLACES the env's own two noise lines
    (with the "none" dynamics it draws the same noise the env does, in
    degrees). Consumes exactly one ``rng.standard_normal(2)`` per call.

Reproducibility: everything is a function of the generators passed in; same
seed -> identical images and commands, different seed -> different ones. We
suggest giving the randomiser its own ``np.random.default_rng(...)`` derived
from the reset seed, so that switching randomisation on does not shift the
grid, obstacle or action-noise streams.

Every field of `Randomization` is documented below with its unit and allowed
range; `(lo, hi)` fields are uniform ranges drawn once per episode.
"""
from __future__ import annotations

import dataclasses
import math
from typing import Any

import cv2
import numpy as np

from ..sim.car import CarSpec
from ..sim.texture import DEFAULT_PALETTE, Palette

Range = tuple[float, float]


def _range(default: Range, lo: float, hi: float, unit: str, doc: str):
    return dataclasses.field(default=default, metadata={"kind": "range", "bounds": (lo, hi), "unit": unit,
                                                         "doc": doc})


def _scalar(default: float, lo: float, hi: float, unit: str, doc: str):
    return dataclasses.field(default=default, metadata={"kind": "scalar", "bounds": (lo, hi), "unit": unit,
                                                         "doc": doc})


BLUR_KERNELS = (0, 3, 5, 7)


@dataclasses.dataclass(frozen=True)
class Randomization:
    """Ranges of the randomised quantities. The defaults are the identity ("none")."""

    # ---- perception: lighting (drawn per episode, shared by all cars)
    brightness: Range = _range((0.0, 0.0), -80, 80, "grey levels",
                               "added to every pixel (after contrast); e.g. (-40, 40)")
    contrast: Range = _range((1.0, 1.0), 0.3, 3.0, "gain",
                             "multiplies the deviation from mid-grey 128; e.g. (0.7, 1.3)")
    hue_shift: Range = _range((0.0, 0.0), -180, 180, "degrees",
                              "rotation of the hue around the grey axis (RGB cameras only); e.g. (-10, 10)")
    saturation: Range = _range((1.0, 1.0), 0.0, 3.0, "gain",
                               "colour saturation gain (RGB cameras only); e.g. (0.7, 1.3)")
    # ---- perception: sensor and optics
    noise_sigma: Range = _range((0.0, 0.0), 0, 30, "grey levels",
                                "standard deviation of per-pixel Gaussian noise, drawn per episode; e.g. (0, 8)")
    blur_kernels: tuple[int, ...] = dataclasses.field(default=(3,), metadata={
        "kind": "choices", "choices": BLUR_KERNELS, "unit": "pixels",
        "doc": "Gaussian blur kernel sizes to choose from per episode (0 = none)"})
    blur_prob: float = _scalar(0.0, 0, 1, "probability", "chance that a frame is blurred")
    shadow_prob: float = _scalar(0.0, 0, 1, "probability", "chance that a frame gets a shadow polygon")
    shadow_strength: Range = _range((0.3, 0.6), 0, 0.95, "fraction",
                                    "how much a shadow darkens the pixels it covers (0 = not, 1 = black)")
    # ---- perception: camera mounting (per car, per episode)
    camera_yaw: Range = _range((0.0, 0.0), -0.3, 0.3, "radians", "camera yaw offset; e.g. (-0.03, 0.03)")
    camera_pitch: Range = _range((0.0, 0.0), -0.3, 0.3, "radians",
                                 "camera pitch offset (positive = more down); e.g. (-0.03, 0.03)")
    camera_height: Range = _range((0.0, 0.0), -0.1, 0.1, "metres", "camera height offset; e.g. (-0.01, 0.01)")
    # ---- perception: the track texture's colours (per episode)
    texture_tint: float = _scalar(0.0, 0, 0.5, "relative",
                                  "max relative change of each RGB channel of the road, floor, border and "
                                  "centre-line colours; e.g. 0.15")
    # ---- dynamics (per car, per episode)
    steer_noise_scale: Range = _range((1.0, 1.0), 0, 10, "multiplier",
                                      "multiplies DeepRacer's steering noise (CarSpec.steer_noise, 0.01 rad)")
    speed_noise_scale: Range = _range((1.0, 1.0), 0, 10, "multiplier",
                                      "multiplies DeepRacer's speed noise (CarSpec.speed_noise, 0.1 m/s)")
    speed_gain: Range = _range((1.0, 1.0), 0.5, 1.5, "multiplier",
                               "multiplies the commanded speed (friction / battery stand-in); e.g. (0.9, 1.1)")
    steer_offset: Range = _range((0.0, 0.0), -10, 10, "degrees",
                                 "added to the commanded steering (a miscalibrated servo); e.g. (-2, 2)")
    grip: Range = _range((1.0, 1.0), 0.3, 1.5, "multiplier",
                         "multiplies the tyres' friction (CarSpec.mu; a dusty or a fresh track); e.g. (0.85, 1.05)")
    motor: Range = _range((1.0, 1.0), 0.3, 1.5, "multiplier",
                          "multiplies the motor's force (CarSpec.accel; a tired battery); e.g. (0.85, 1.05)")

    # ------------------------------------------------------------ construction
    def __post_init__(self):
        for f in dataclasses.fields(self):
            value = getattr(self, f.name)
            meta = f.metadata
            kind = meta["kind"]
            if kind == "range":
                try:
                    lo, hi = (float(v) for v in value)
                except (TypeError, ValueError):
                    raise ValueError(f"randomize: {f.name} must be a (low, high) pair "
                                     f"({meta['unit']}), got {value!r}") from None
                b_lo, b_hi = meta["bounds"]
                if not (math.isfinite(lo) and math.isfinite(hi)) or lo > hi or lo < b_lo or hi > b_hi:
                    raise ValueError(f"randomize: {f.name} range {value!r} is invalid; need "
                                     f"{b_lo:g} <= low <= high <= {b_hi:g} ({meta['unit']})")
                object.__setattr__(self, f.name, (lo, hi))
            elif kind == "scalar":
                try:
                    v = float(value)
                except (TypeError, ValueError):
                    raise ValueError(f"randomize: {f.name} must be a number ({meta['unit']}), "
                                     f"got {value!r}") from None
                b_lo, b_hi = meta["bounds"]
                if not (b_lo <= v <= b_hi):
                    raise ValueError(f"randomize: {f.name}={value!r} out of range {b_lo:g} .. {b_hi:g} "
                                     f"({meta['unit']})")
                object.__setattr__(self, f.name, v)
            elif kind == "choices":
                if isinstance(value, (int, np.integer)):
                    value = (value,)
                try:
                    ks = tuple(int(k) for k in value)
                except (TypeError, ValueError):
                    raise ValueError(f"randomize: {f.name} must be a list of kernel sizes from "
                                     f"{meta['choices']}, got {value!r}") from None
                if not ks or any(k not in meta["choices"] for k in ks):
                    raise ValueError(f"randomize: {f.name}={value!r}: each must be one of {meta['choices']}")
                object.__setattr__(self, f.name, ks)

    @classmethod
    def preset(cls, name: str) -> "Randomization":
        """The named preset: "none", "mild" or "strong"."""
        try:
            return cls(**PRESETS[name])
        except (KeyError, TypeError):
            raise ValueError(f"randomize: unknown preset {name!r}; choose one of {sorted(PRESETS)}") from None

    @classmethod
    def from_config(cls, config: "None | str | dict | Randomization") -> "Randomization":
        """From the env's `randomize=` keyword: None, a preset name, or a dict of overrides."""
        if config is None:
            return cls()
        if isinstance(config, Randomization):
            return config
        if isinstance(config, str):
            return cls.preset(config)
        if isinstance(config, dict):
            overrides = dict(config)
            base = overrides.pop("preset", "none")
            names = {f.name for f in dataclasses.fields(cls)}
            unknown = sorted(k for k in overrides if k not in names)
            if unknown:
                raise ValueError(f"randomize: unknown key {unknown[0]!r}; known keys: preset, "
                                 + ", ".join(sorted(names)))
            fields = dict(PRESETS[base]) if base in PRESETS else None
            if fields is None:
                raise ValueError(f"randomize: unknown preset {base!r}; choose one of {sorted(PRESETS)}")
            fields.update(overrides)
            return cls(**fields)
        raise ValueError(f"randomize: expected None, a preset name or a dict, got {type(config).__name__}")

    @classmethod
    def describe(cls) -> str:
        """One line per field: name, unit, allowed range and meaning."""
        lines = []
        for f in dataclasses.fields(cls):
            m = f.metadata
            allowed = m.get("bounds", m.get("choices"))
            lines.append(f"{f.name} [{m['unit']}, allowed {allowed}]: {m['doc']}")
        return "\n".join(lines)

    # ---------------------------------------------------------------- queries
    @property
    def perception_enabled(self) -> bool:
        """Whether `apply_image` changes anything (camera jitter and tint are separate)."""
        return (self.brightness != (0.0, 0.0) or self.contrast != (1.0, 1.0) or self.hue_shift != (0.0, 0.0)
                or self.saturation != (1.0, 1.0) or self.noise_sigma[1] > 0
                or (self.blur_prob > 0 and any(self.blur_kernels)) or self.shadow_prob > 0)

    @property
    def camera_enabled(self) -> bool:
        return any(r != (0.0, 0.0) for r in (self.camera_yaw, self.camera_pitch, self.camera_height))

    @property
    def dynamics_enabled(self) -> bool:
        return (self.steer_noise_scale != (1.0, 1.0) or self.speed_noise_scale != (1.0, 1.0)
                or self.speed_gain != (1.0, 1.0) or self.steer_offset != (0.0, 0.0) or self.grip != (1.0, 1.0)
                or self.motor != (1.0, 1.0))

    @property
    def enabled(self) -> bool:
        return self.perception_enabled or self.camera_enabled or self.dynamics_enabled or self.texture_tint > 0

    # ---------------------------------------------------------------- drawing
    def draw_episode(self, rng: np.random.Generator, num_cars: int = 1) -> "EpisodeDraw":
        """Everything fixed for one episode, drawn from `rng` (a numpy Generator)."""
        def u(r: Range, size=None):
            return rng.uniform(r[0], r[1], size)

        palette = DEFAULT_PALETTE
        if self.texture_tint > 0:
            t = self.texture_tint

            def tint(rgb):
                gains = rng.uniform(1 - t, 1 + t, 3)
                return tuple(int(np.clip(round(c * g), 0, 255)) for c, g in zip(rgb, gains))

            palette = dataclasses.replace(palette, floor=tint(palette.floor), road=tint(palette.road),
                                          border=tint(palette.border), centre=tint(palette.centre))
        jitter = np.stack([u(self.camera_yaw, num_cars), u(self.camera_pitch, num_cars),
                           u(self.camera_height, num_cars)], axis=1)
        return EpisodeDraw(
            palette=palette,
            camera_jitter=tuple(tuple(float(v) for v in row) for row in jitter),
            brightness=float(u(self.brightness)),
            contrast=float(u(self.contrast)),
            hue_shift=float(u(self.hue_shift)),
            saturation=float(u(self.saturation)),
            noise_sigma=float(u(self.noise_sigma)),
            blur_kernel=int(self.blur_kernels[int(rng.integers(len(self.blur_kernels)))]),
            blur_prob=self.blur_prob,
            shadow_prob=self.shadow_prob,
            shadow_strength=self.shadow_strength,
            steer_offset=tuple(float(v) for v in u(self.steer_offset, num_cars)),
            speed_gain=tuple(float(v) for v in u(self.speed_gain, num_cars)),
            steer_noise_scale=tuple(float(v) for v in u(self.steer_noise_scale, num_cars)),
            speed_noise_scale=tuple(float(v) for v in u(self.speed_noise_scale, num_cars)),
            seed=int(rng.integers(2**63 - 1)),
            grip=tuple(float(v) for v in u(self.grip, num_cars)),  # drawn last: the older draws stay put
            motor=tuple(float(v) for v in u(self.motor, num_cars)),
        )


PRESETS: dict[str, dict[str, Any]] = {
    "none": {},
    "mild": dict(brightness=(-20, 20), contrast=(0.85, 1.15), hue_shift=(-5, 5), saturation=(0.85, 1.15),
                 noise_sigma=(0, 4), blur_kernels=(3,), blur_prob=0.1, shadow_prob=0.2,
                 shadow_strength=(0.2, 0.4), camera_yaw=(-0.02, 0.02), camera_pitch=(-0.02, 0.02),
                 camera_height=(-0.01, 0.01), texture_tint=0.1, steer_noise_scale=(1.0, 1.5),
                 speed_noise_scale=(1.0, 1.5), speed_gain=(0.95, 1.05), steer_offset=(-1, 1),
                 grip=(0.9, 1.05), motor=(0.9, 1.05)),
    "strong": dict(brightness=(-40, 40), contrast=(0.7, 1.3), hue_shift=(-15, 15), saturation=(0.6, 1.4),
                   noise_sigma=(0, 8), blur_kernels=(3, 5), blur_prob=0.3, shadow_prob=0.5,
                   shadow_strength=(0.3, 0.6), camera_yaw=(-0.05, 0.05), camera_pitch=(-0.05, 0.05),
                   camera_height=(-0.02, 0.02), texture_tint=0.25, steer_noise_scale=(1.0, 3.0),
                   speed_noise_scale=(1.0, 3.0), speed_gain=(0.9, 1.1), steer_offset=(-3, 3),
                   grip=(0.75, 1.1), motor=(0.75, 1.1)),
}

NOISE_BANK_SCALE = 2  # the noise field is this many times the image in each direction
SHADOW_BANK = 8  # shadow masks drawn per episode and image shape


@dataclasses.dataclass
class EpisodeDraw:
    """The randomisation fixed for one episode (see `Randomization.draw_episode`).

    Per-car tuples are indexed by car (learning cars then bots, as the env's
    `world` orders them). Shadow masks and the noise field are made lazily per
    image shape from `seed`, so they do not depend on the per-frame stream.
    """

    palette: Palette
    camera_jitter: tuple  # per car (d_yaw rad, d_pitch rad, d_height m)
    brightness: float
    contrast: float
    hue_shift: float
    saturation: float
    noise_sigma: float
    blur_kernel: int
    blur_prob: float
    shadow_prob: float
    shadow_strength: Range
    steer_offset: tuple  # per car, degrees
    speed_gain: tuple  # per car
    steer_noise_scale: tuple  # per car
    speed_noise_scale: tuple  # per car
    seed: int
    grip: tuple = ()  # per car, the tyres' friction multiplier
    motor: tuple = ()  # per car, the motor's force multiplier
    _cache: dict = dataclasses.field(default_factory=dict, repr=False, compare=False)

    # --------------------------------------------------------------- caches
    def _lighting(self, channels: int):
        """The affine colour map for cv2.transform: 1x2 (gray) or 3x4 (RGB), or None when the identity."""
        key = ("light", channels)
        if key not in self._cache:
            c, b = self.contrast, self.brightness
            identity_gray = abs(c - 1) < 1e-9 and abs(b) < 1e-9
            if channels == 1:
                value = None if identity_gray else np.array([[c, 128 * (1 - c) + b]], np.float32)
            else:
                m = _hue_saturation_matrix(self.hue_shift, self.saturation)
                if identity_gray and np.allclose(m, np.eye(3)):
                    value = None
                else:
                    value = np.zeros((3, 4), np.float32)
                    value[:, :3] = c * m
                    value[:, 3] = 128 * (1 - c) + b
            self._cache[key] = value
        return self._cache[key]

    def _noise(self, shape):
        """(positive, negative) uint8 noise fields of NOISE_BANK_SCALE x the image size, or None."""
        key = ("noise", shape)
        if key not in self._cache:
            if self.noise_sigma * 3 < 0.5:
                value = None
            else:
                h, w = shape[0], shape[1]
                rng = np.random.default_rng([self.seed, 1])
                field = rng.standard_normal((NOISE_BANK_SCALE * h, NOISE_BANK_SCALE * w) + tuple(shape[2:]),
                                            dtype=np.float32) * self.noise_sigma
                field = np.clip(np.round(field), -255, 255)
                value = (np.maximum(field, 0).astype(np.uint8), np.maximum(-field, 0).astype(np.uint8))
            self._cache[key] = value
        return self._cache[key]

    def _shadows(self, shape):
        """SHADOW_BANK uint8 multiplier images (255 = unshaded) of the image's shape."""
        key = ("shadow", shape)
        if key not in self._cache:
            h, w = shape[0], shape[1]
            rng = np.random.default_rng([self.seed, 2])
            masks = []
            for _ in range(SHADOW_BANK):
                strength = rng.uniform(*self.shadow_strength)
                mask = np.full((h, w), 255, np.uint8)
                # a convex-ish polygon from 3-6 points, biased to touch an image border
                k = int(rng.integers(3, 7))
                cx, cy = rng.uniform(0, w), rng.uniform(0, h)
                angles = np.sort(rng.uniform(0, 2 * np.pi, k))
                radii = rng.uniform(0.3, 0.9, k) * max(h, w)
                pts = np.stack([cx + radii * np.cos(angles), cy + radii * np.sin(angles)], axis=1)
                cv2.fillPoly(mask, [np.round(pts).astype(np.int32)], int(round(255 * (1 - strength))),
                             lineType=cv2.LINE_AA)
                soft = max(3, (min(h, w) // 20) | 1)
                mask = cv2.GaussianBlur(mask, (soft, soft), 0)
                if len(shape) == 3 and shape[2] == 3:
                    mask = cv2.merge([mask, mask, mask])
                masks.append(mask)
            self._cache[key] = masks
        return self._cache[key]


def _hue_saturation_matrix(hue_deg: float, saturation: float) -> np.ndarray:
    """3x3 RGB matrix: rotate hue by `hue_deg` about the grey axis, then scale saturation (keeps grey)."""
    a = math.radians(hue_deg)
    cos, sin = math.cos(a), math.sin(a)
    k = np.full((3, 3), 1.0 / 3.0)
    # rotation about the (1,1,1)/sqrt(3) axis (Rodrigues)
    cross = np.array([[0, -1, 1], [1, 0, -1], [-1, 1, 0]]) / math.sqrt(3)
    rot = cos * np.eye(3) + sin * cross + (1 - cos) * k
    luma = np.array([0.299, 0.587, 0.114])
    sat = saturation * np.eye(3) + (1 - saturation) * np.tile(luma, (3, 1))
    return sat @ rot


def apply_image(image: np.ndarray, rng: np.random.Generator, draw: EpisodeDraw) -> np.ndarray:
    """Randomise one camera frame: uint8 (H, W, 1|3) in, a new uint8 array of the same shape out."""
    shape = image.shape
    h, w = shape[0], shape[1]
    channels = shape[2] if image.ndim == 3 else 1
    u = rng.random(5)  # blur?, shadow?, which shadow, noise row, noise column
    out = image.reshape(h, w) if channels == 1 else image
    if draw.shadow_prob > 0 and u[1] < draw.shadow_prob:
        masks = draw._shadows(shape if channels == 3 else (h, w))
        out = cv2.multiply(out, masks[int(u[2] * len(masks))], scale=1.0 / 255)
    if draw.blur_kernel and u[0] < draw.blur_prob:
        out = cv2.GaussianBlur(out, (draw.blur_kernel, draw.blur_kernel), 0)
    light = draw._lighting(channels)
    if light is not None:
        out = cv2.transform(out, light)
    noise = draw._noise((h, w) if channels == 1 else shape)
    if noise is not None:
        r0 = int(u[3] * (NOISE_BANK_SCALE - 1) * h)
        c0 = int(u[4] * (NOISE_BANK_SCALE - 1) * w)
        pos, neg = noise
        out = cv2.subtract(cv2.add(out, pos[r0:r0 + h, c0:c0 + w]), neg[r0:r0 + h, c0:c0 + w])
    if np.shares_memory(out, image):  # nothing applied this frame
        out = out.copy()
    return out.reshape(shape)


def apply_command(steer_deg: float, speed: float, draw: EpisodeDraw, rng: np.random.Generator, car: int = 0,
                  spec: CarSpec | None = None) -> tuple[float, float]:
    """Randomise car `car`'s command: offset, gain and scaled DeepRacer noise. Returns (steer_deg, speed)."""
    spec = spec if spec is not None else _DEFAULT_SPEC
    z = rng.standard_normal(2)
    steer = (steer_deg + draw.steer_offset[car]
             + math.degrees(spec.steer_noise) * draw.steer_noise_scale[car] * z[0])
    speed = speed * draw.speed_gain[car] + spec.speed_noise * draw.speed_noise_scale[car] * z[1]
    return float(steer), float(speed)


_DEFAULT_SPEC = CarSpec()
