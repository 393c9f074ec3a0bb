"""`multirace explain`: Grad-CAM heat maps of what a camera agent looks at.

``explain(agent_file, track=..., steps=150, out=None, replay=None) -> dict``
drives the agent alone on the track (a 1-car time trial, from its camera
only, greedy actions as in a race) and, for every camera frame it acts on,
computes Grad-CAM (Selvaraju et al. 2017) of the action it chose:

- the score is the chosen action's logit (discrete action spaces) or, for a
  continuous space, the steering mean signed by its direction (``target=
  "steer"``, evidence for steering the way it steers) or the speed mean
  (``target="speed"``);
- the activations are those of the last convolutional layer of the net's
  trunk (after its ReLU); the channel weights are the spatial means of the
  score's gradient, the map is ``relu(sum_k w_k A_k)``, upsampled bilinearly
  to the camera image size and scaled to [0, 1] per frame;
- the overlay is the camera frame blended with ``cv2.applyColorMap(JET)``.

Outputs: an MP4 (``out`` ending in ``.mp4``, one overlay per step, scaled up
`scale` times) or a PNG strip (``.png``: up to `strip_frames` evenly spaced
steps side by side, camera above, overlay below); with ``replay=...`` the run
is recorded as a race replay (`replay.ReplayRecorder`) that also holds the
overlays as JPEG images at ``explain/car_0`` on the same ``step`` /
``race_time`` time lines, shown in the replay's blueprint.

Where the heat lies is measured against the ground truth of the scene:
`scene_labels` warps a per-texel label map of the track texture (floor, road,
border, centre line) with the fast renderer's ground homography, exactly as
the camera image's ground is drawn, so every image pixel is labelled floor,
road, border, centre line or sky. The result reports, averaged over frames,
``heat_on_track`` (the share of heat mass on road + border + centre-line
pixels) against ``track_fraction`` (the share of the image those pixels
cover): a map that ignored the image content would give the two equal.
"""
from __future__ import annotations

import math
from pathlib import Path

import cv2
import numpy as np
import torch
from torch import nn

from ..atomic import write_bytes
from ..environment.race_env import ACTION_HZ
from ..racing.agentfile import load_agent
from ..racing.entrant import Controller
from ..racing.runner import RaceConfig, run_race
from ..recording.replay import ReplayRecorder
from ..sensors.camera import camera_pose
from ..sensors.fast_renderer import FastRenderer

FLOOR, ROAD, BORDER, CENTRE, SKY = 0, 1, 2, 3, 4
LABEL_NAMES = ("floor", "road", "border", "centre", "sky")
TRACK_LABELS = (ROAD, BORDER, CENTRE)
HEAT_ALPHA = 0.45  # weight of the colour map in the overlay
DEFAULT_STEPS = 150


# ------------------------------------------------------------------ Grad-CAM
def last_conv_activation(net: nn.Module) -> nn.Module:
    """The module whose output is the last conv layer's activation map (its ReLU, if one follows)."""
    modules = list(net.conv) if isinstance(net.conv, nn.Sequential) else list(net.conv.modules())
    index = max((k for k, m in enumerate(modules) if isinstance(m, nn.Conv2d)), default=None)
    if index is None:
        raise ValueError("explain: the net has no convolutional layer")
    if index + 1 < len(modules) and isinstance(modules[index + 1], (nn.ReLU, nn.LeakyReLU, nn.ELU)):
        return modules[index + 1]
    return modules[index]


def _pair(v) -> tuple[float, float]:
    return (float(v[0]), float(v[1])) if isinstance(v, (tuple, list)) else (float(v), float(v))


def cell_geometry(net: nn.Module, layer: nn.Module):
    """Where the cells of `layer`'s output map sit in the input image.

    Returns ((row0, col0), (row_step, col_step)): the centre of cell (0, 0)'s receptive field,
    in input pixel coordinates (pixel centres at integers), and the spacing of cell centres.
    """
    start, jump = [0.0, 0.0], [1.0, 1.0]
    for module in net.conv:
        if isinstance(module, (nn.Conv2d, nn.AvgPool2d, nn.MaxPool2d)):
            kernel, stride = _pair(module.kernel_size), _pair(module.stride or module.kernel_size)
            padding = _pair(module.padding)
            dilation = _pair(getattr(module, "dilation", 1))
            for a in range(2):
                start[a] += ((kernel[a] - 1) * dilation[a] / 2 - padding[a]) * jump[a]
                jump[a] *= stride[a]
        if module is layer:
            return tuple(start), tuple(jump)
    raise ValueError("explain: layer not found in the net's trunk")


class GradCam:
    """Grad-CAM of a `nets.CameraNet` on single uint8 camera images, (H, W) grey or (H, W, 3)."""

    def __init__(self, net: nn.Module, discrete: bool, target: str = "steer", align: bool = True):
        if target not in ("steer", "speed"):
            raise ValueError(f"explain: target must be 'steer' or 'speed', got {target!r}")
        self.net, self.discrete, self.target, self.align = net, discrete, target, align
        self.layer = last_conv_activation(net)
        self.geometry = cell_geometry(net, self.layer)
        self._activation = None
        self._handle = self.layer.register_forward_hook(self._hook)

    def _hook(self, module, inputs, output):
        self._activation = output

    def close(self) -> None:
        self._handle.remove()

    def __call__(self, image: np.ndarray):
        """(heat (H, W) float32 in [0, 1], raw net output row, score index).

        The score index is the chosen action (discrete), or 0 / 1 for the steering / speed mean.
        """
        image = np.ascontiguousarray(image)
        height, width = image.shape[:2]
        self.net.zero_grad(set_to_none=True)
        with torch.enable_grad():
            out = self.net(torch.from_numpy(image))
            activation = self._activation
            if self.discrete:
                index = int(out[0].argmax())
                score = out[0, index]
            else:
                index = 0 if self.target == "steer" else 1
                score = out[0, index]
                if index == 0 and float(score.detach()) < 0:
                    score = -score  # evidence for steering the way it steers
            (grad,) = torch.autograd.grad(score, activation)
        weights = grad[0].mean(dim=(1, 2))  # (K,)
        cam = torch.relu((weights[:, None, None] * activation[0]).sum(0)).detach().numpy().astype(np.float32)
        heat = self.upsample(cam, height, width)
        heat = np.maximum(heat, 0.0)
        peak = float(heat.max())
        heat = heat / peak if peak > 0 else np.zeros_like(heat)
        return heat, out.detach().numpy()[0], index

    def upsample(self, cam: np.ndarray, height: int, width: int) -> np.ndarray:
        """The cell map at image size: bilinear between the cells' receptive-field centres (`align`),
        held constant beyond the outer centres; or (not `align`) stretched over the whole image."""
        if not self.align:
            return cv2.resize(cam, (width, height), interpolation=cv2.INTER_LINEAR)
        (row0, col0), (row_step, col_step) = self.geometry
        to_image = np.array([[col_step, 0.0, col0], [0.0, row_step, row0]])
        return cv2.warpAffine(cam, to_image, (width, height), flags=cv2.INTER_LINEAR,
                              borderMode=cv2.BORDER_REPLICATE)


def overlay(image: np.ndarray, heat: np.ndarray, alpha: float = HEAT_ALPHA) -> np.ndarray:
    """The camera image (uint8 grey (H, W) or RGB (H, W, 3)) blended with the JET colour map of `heat`; uint8 RGB."""
    image = np.asarray(image)
    rgb = cv2.cvtColor(image, cv2.COLOR_GRAY2RGB) if image.ndim == 2 else image
    colours = cv2.cvtColor(cv2.applyColorMap(np.uint8(np.clip(heat, 0, 1) * 255), cv2.COLORMAP_JET),
                           cv2.COLOR_BGR2RGB)
    return cv2.addWeighted(rgb, 1.0 - alpha, colours, alpha, 0.0)


# ------------------------------------------------------------------ the scene's ground truth
def texture_labels(texture) -> np.ndarray:
    """Per-texel label (FLOOR, ROAD, BORDER, CENTRE) of a `TrackTexture`: the nearest palette colour."""
    cached = getattr(texture, "_explain_labels", None)
    if cached is not None:
        return cached
    p = texture.palette
    palette = np.array([p.floor, p.road, p.border, p.centre], dtype=np.int32)
    rgb = texture.rgb.astype(np.int32)
    best = np.full(rgb.shape[:2], np.iinfo(np.int32).max, dtype=np.int64)
    labels = np.zeros(rgb.shape[:2], dtype=np.uint8)
    for k, colour in enumerate(palette):
        d = ((rgb - colour) ** 2).sum(axis=-1)
        closer = d < best
        labels[closer] = k
        best[closer] = d[closer]
    texture._explain_labels = labels
    return labels


def scene_labels(env, car: int = 0, renderer: FastRenderer | None = None) -> np.ndarray:
    """Label (FLOOR, ROAD, BORDER, CENTRE, SKY) of every pixel of car `car`'s camera image now.

    The ground is warped with the fast renderer's ground homography (nearest texel, as the
    camera image is drawn); other cars and boxes are not drawn (labels describe the ground).
    """
    spec = env.camera
    renderer = renderer if renderer is not None else FastRenderer(spec, env.texture)
    here = env.race_state.cars[car]
    pose = camera_pose(spec, (here.x, here.y, here.yaw))
    labels = cv2.warpPerspective(texture_labels(env.texture), renderer.ground_homography(pose),
                                 (spec.width, spec.height), flags=cv2.INTER_NEAREST,
                                 borderMode=cv2.BORDER_CONSTANT, borderValue=FLOOR)
    labels[: renderer.horizon_row(pose)] = SKY
    return labels


def heat_shares(heat: np.ndarray, labels: np.ndarray) -> dict:
    """Share of the heat mass and of the image area on each label, and on the track (road+border+centre)."""
    total = float(heat.sum())
    on_track = np.isin(labels, TRACK_LABELS)
    out = {"track_fraction": float(on_track.mean()),
           "heat_on_track": float(heat[on_track].sum() / total) if total > 0 else math.nan}
    for k, name in enumerate(LABEL_NAMES):
        mask = labels == k
        out[f"area_{name}"] = float(mask.mean())
        out[f"heat_{name}"] = float(heat[mask].sum() / total) if total > 0 else math.nan
    return out


# ------------------------------------------------------------------ the run
class ExplainRecorder(ReplayRecorder):
    """A race replay recorder that also holds the Grad-CAM overlays (``explain/car_0``) and shows them."""

    layout = "explain"

    def log_heat(self, step: int, race_time: float, image_rgb: np.ndarray) -> None:
        """Record one overlay (uint8 RGB) as a JPEG image at `step` / `race_time`."""
        self.log_image("explain/car_0", step, race_time, image_rgb)


class ExplainController(Controller):
    """Drives with an agent's greedy actions and keeps, for every frame it acts on, its Grad-CAM evidence."""

    def __init__(self, agent, target: str, align: bool, recorder: ExplainRecorder | None, keep_images: bool):
        self.agent, self.name, self.recorder, self.keep_images = agent, agent.name, recorder, keep_images
        self.cam = GradCam(agent.net, agent.action_space.discrete, target, align=align)
        self.images, self.heats, self.labels, self.overlays, self.rows = [], [], [], [], []

    def reset(self, env, car: int) -> None:
        super().reset(env, car)
        self.renderer = FastRenderer(env.camera, env.texture)

    def act(self, observation, info):
        heat, output, _ = self.cam(observation)
        labels = scene_labels(self.env, self.car, self.renderer)
        shares = heat_shares(heat, labels)
        if not math.isnan(shares["heat_on_track"]):
            self.rows.append(shares)
        pic = overlay(observation, heat)
        if self.recorder is not None:
            self.recorder.log_heat(self.env.steps, self.env.sim_time, pic)
        self.overlays.append(pic)
        if self.keep_images:
            self.images.append(np.array(observation))
            self.heats.append(heat)
            self.labels.append(labels)
        steer, speed = self.agent.action_space.command(self.agent.decide(output))
        return float(steer), float(speed)


def explain(agent_file, track: str = "reinvent_base", steps: int = DEFAULT_STEPS, out=None, replay=None,
            reverse: bool = False, seed: int = 0, target: str = "steer", scale: int = 3,
            strip_frames: int = 8, keep_frames: bool = False, align: bool = True) -> dict:
    """Drive an agent and compute Grad-CAM of its chosen actions (see the module docstring).

    Returns {"agent", "track", "frames", "out", "replay", "heat_on_track", "track_fraction",
    "lift" (heat_on_track / track_fraction), "lines_lift" (heat share on border + centre-line
    pixels over their area share, per frame, averaged), "shares" (mean per-label heat and area
    shares), "status"} and, with `keep_frames`, "images", "heats", "labels" (lists, one per frame).
    """
    if out is not None and Path(out).suffix.lower() not in (".mp4", ".png"):
        raise ValueError(f"explain: --out must end in .mp4 or .png, got {out}")
    agent = load_agent(agent_file, step_budget=None)
    if agent.sensors.names != ["FRONT_FACING_CAMERA"]:
        raise ValueError(f"{agent_file}: explain computes Grad-CAM of single-camera agents; this agent reads "
                         f"{agent.sensors.names} (sensor in its model_metadata)")
    height, width, channels = agent.image_shape
    config = RaceConfig(track=track, reverse=reverse, race="time_trial", laps=1, seed=seed, max_steps=int(steps),
                        camera=(height, width), grayscale=channels == 1)
    recorder = ExplainRecorder(replay) if replay else None
    driver = ExplainController(agent, target, align, recorder,
                               keep_images=keep_frames or (out is not None and str(out).lower().endswith(".png")))
    try:
        result = run_race([driver], config, recorders=[recorder] if recorder is not None else [])
    except BaseException:
        if recorder is not None:
            recorder.close()
        raise
    finally:
        driver.cam.close()
    rows, overlays = driver.rows, driver.overlays
    written = None
    if out is not None:
        written = _write(out, overlays, driver.images, driver.heats, scale, strip_frames, ACTION_HZ)
    mean = {k: float(np.mean([r[k] for r in rows])) for k in rows[0]} if rows else {}
    result = {
        "agent": agent.name, "track": track, "frames": len(overlays), "out": written,
        "replay": str(replay) if replay else None, "status": result["cars"][0]["status"],
        "heat_on_track": mean.get("heat_on_track", math.nan), "track_fraction": mean.get("track_fraction", math.nan),
        "frames_with_heat": len(rows), "shares": mean,
    }
    lifts = [(r["heat_border"] + r["heat_centre"]) / (r["area_border"] + r["area_centre"])
             for r in rows if r["area_border"] + r["area_centre"] > 0]
    result["lines_lift"] = float(np.mean(lifts)) if lifts else math.nan
    result["lift"] = (result["heat_on_track"] / result["track_fraction"]
                      if result["track_fraction"] and not math.isnan(result["track_fraction"]) else math.nan)
    if keep_frames:
        result.update(images=driver.images, heats=driver.heats, labels=driver.labels)
    return result


def _write(out, overlays, images, heats, scale: int, strip_frames: int, fps: float) -> str:
    out = Path(out)
    scale = max(1, int(scale))

    def up(pic):
        return cv2.resize(pic, (pic.shape[1] * scale, pic.shape[0] * scale), interpolation=cv2.INTER_NEAREST)

    if out.suffix.lower() == ".mp4":
        from ..recording.video import write_video

        write_video((up(p) for p in overlays), out, fps=fps)
        return str(out)
    if out.suffix.lower() == ".png":
        if not overlays:
            raise ValueError("explain: no frames to write")
        count = max(1, min(int(strip_frames), len(overlays)))
        picks = np.unique(np.linspace(0, len(overlays) - 1, count).round().astype(int))
        gap = 4
        tiles = []
        for k in picks:
            camera = overlay(images[k], np.zeros_like(heats[k]), alpha=0.0)
            column = np.concatenate([up(camera), np.full((gap, camera.shape[1] * scale, 3), 255, np.uint8),
                                     up(overlays[k])], axis=0)
            tiles += [column, np.full((column.shape[0], gap, 3), 255, np.uint8)]
        strip = np.concatenate(tiles[:-1], axis=1)
        ok, png = cv2.imencode(".png", cv2.cvtColor(strip, cv2.COLOR_RGB2BGR))
        if not ok:
            raise ValueError(f"explain: cannot encode the PNG strip for {out}")
        return str(write_bytes(out, png.tobytes()))
    raise ValueError(f"explain: --out must end in .mp4 or .png, got {out}")
