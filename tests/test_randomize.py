"""Domain randomisation: determinism, the direction of each effect, config errors, dynamics."""
from __future__ import annotations

import dataclasses

import cv2
import numpy as np
import pytest

from multirace.environment.race_env import RaceEnv
from multirace.environment.randomize import EpisodeDraw, Randomization, apply_command, apply_image
from multirace.sim.texture import DEFAULT_PALETTE


@pytest.fixture(scope="module")
def camera_images():
    """Real camera frames from the env: gray (H, W, 1) and RGB (H, W, 3)."""
    images = {}
    for gray in (True, False):
        env = RaceEnv(num_cars=2, grayscale=gray, race="object_avoidance")
        try:
            obs, _ = env.reset(seed=3)
            images["gray" if gray else "rgb"] = obs["car_0"].copy()
        finally:
            env.close()
    return images


def _draw(rand: Randomization, seed=0, **overrides) -> EpisodeDraw:
    draw = rand.draw_episode(np.random.default_rng(seed), num_cars=4)
    return dataclasses.replace(draw, **overrides) if overrides else draw


def _frames(rand, image, seed, count=6):
    """`count` randomised frames of `image` from one episode seeded with `seed`."""
    draw = rand.draw_episode(np.random.default_rng(seed), num_cars=2)
    rng = np.random.default_rng([seed, 99])
    return [apply_image(image, rng, draw) for _ in range(count)]


@pytest.mark.parametrize("kind", ["gray", "rgb"])
@pytest.mark.parametrize("preset", ["mild", "strong"])
def test_same_seed_identical_different_seed_different(camera_images, kind, preset):
    image = camera_images[kind]
    rand = Randomization.preset(preset)
    a, b, c = _frames(rand, image, 7), _frames(rand, image, 7), _frames(rand, image, 8)
    for x, y in zip(a, b):
        assert x.shape == image.shape and x.dtype == np.uint8
        assert np.array_equal(x, y)
    assert any(not np.array_equal(x, z) for x, z in zip(a, c))
    assert any(not np.array_equal(x, image) for x in a)


def test_input_not_modified_and_none_is_identity(camera_images):
    image = camera_images["gray"]
    before = image.copy()
    out = apply_image(image, np.random.default_rng(0), _draw(Randomization.preset("none")))
    assert np.array_equal(out, before) and np.array_equal(image, before)
    assert out is not image and not np.shares_memory(out, image)
    strong = apply_image(image, np.random.default_rng(0), _draw(Randomization.preset("strong")))
    assert np.array_equal(image, before)
    assert strong.shape == image.shape


def test_brightness_and_contrast_directions(camera_images):
    flat = np.full((120, 160, 1), 100, np.uint8)
    rng = np.random.default_rng(0)
    up = apply_image(flat, rng, _draw(Randomization(brightness=(30, 30))))
    down = apply_image(flat, rng, _draw(Randomization(brightness=(-30, -30))))
    assert up.mean() == pytest.approx(130, abs=1) and down.mean() == pytest.approx(70, abs=1)
    image = camera_images["gray"]
    high = apply_image(image, rng, _draw(Randomization(contrast=(1.3, 1.3))))
    low = apply_image(image, rng, _draw(Randomization(contrast=(0.7, 0.7))))
    assert high.astype(float).std() > image.astype(float).std() > low.astype(float).std()


def test_noise_raises_std_of_flat_image():
    flat = np.full((120, 160, 1), 128, np.uint8)
    rand = Randomization(noise_sigma=(6, 6))
    out = apply_image(flat, np.random.default_rng(0), _draw(rand))
    assert out.astype(float).std() == pytest.approx(6, rel=0.15)
    assert out.astype(float).mean() == pytest.approx(128, abs=0.5)
    # the noise moves from frame to frame
    out2 = apply_image(flat, np.random.default_rng(1), _draw(rand))
    assert not np.array_equal(out, out2)


def test_blur_smooths(camera_images):
    image = camera_images["gray"]
    rand = Randomization(blur_kernels=(5,), blur_prob=1.0)
    out = apply_image(image, np.random.default_rng(0), _draw(rand))

    def sharpness(img):
        return cv2.Laplacian(img.reshape(img.shape[:2]), cv2.CV_64F).var()

    assert sharpness(out) < 0.7 * sharpness(image)


def test_shadows_darken_a_region():
    flat = np.full((120, 160, 3), 200, np.uint8)
    rand = Randomization(shadow_prob=1.0, shadow_strength=(0.5, 0.5))
    out = apply_image(flat, np.random.default_rng(0), _draw(rand)).astype(int)
    assert out.max() <= 200
    assert out.min() <= 110  # the shadow's core is about half as bright
    assert (out < 190).mean() > 0.02  # a real region, not a speck
    never = apply_image(flat, np.random.default_rng(0), _draw(Randomization(shadow_prob=0.0)))
    assert np.array_equal(never, flat)


def test_hue_and_saturation_rgb_only():
    red = np.zeros((120, 160, 3), np.uint8)
    red[..., 0] = 200
    rng = np.random.default_rng(0)
    shifted = apply_image(red, rng, _draw(Randomization(hue_shift=(60, 60))))
    assert shifted[..., 1].mean() > 50  # red rotated towards yellow/green
    grey = apply_image(red, rng, _draw(Randomization(saturation=(0.0, 0.0))))
    assert np.ptp(grey[0, 0].astype(int)) <= 1  # desaturated: R = G = B
    gray_img = np.full((120, 160, 1), 90, np.uint8)
    assert np.array_equal(apply_image(gray_img, rng, _draw(Randomization(hue_shift=(60, 60), saturation=(0, 0)))),
                          gray_img)


def test_episode_draw_camera_jitter_palette_and_ranges():
    rand = Randomization.preset("strong")
    draw = rand.draw_episode(np.random.default_rng(4), num_cars=5)
    assert len(draw.camera_jitter) == 5 and len(set(draw.camera_jitter)) == 5
    for d_yaw, d_pitch, d_height in draw.camera_jitter:
        assert rand.camera_yaw[0] <= d_yaw <= rand.camera_yaw[1]
        assert rand.camera_pitch[0] <= d_pitch <= rand.camera_pitch[1]
        assert rand.camera_height[0] <= d_height <= rand.camera_height[1]
    assert draw.palette != DEFAULT_PALETTE and draw.palette.sky == DEFAULT_PALETTE.sky
    for name in ("road", "floor", "border"):
        for c, c0 in zip(getattr(draw.palette, name), getattr(DEFAULT_PALETTE, name)):
            assert abs(c - c0) <= c0 * rand.texture_tint + 1
    assert rand.brightness[0] <= draw.brightness <= rand.brightness[1]
    assert draw.blur_kernel in rand.blur_kernels
    none = Randomization.preset("none").draw_episode(np.random.default_rng(4), num_cars=2)
    assert none.palette == DEFAULT_PALETTE and none.camera_jitter == ((0, 0, 0), (0, 0, 0))


def test_apply_command_dynamics():
    draw = _draw(Randomization(steer_offset=(2, 2), speed_gain=(1.1, 1.1), steer_noise_scale=(0, 0),
                               speed_noise_scale=(0, 0)))
    steer, speed = apply_command(5.0, 2.0, draw, np.random.default_rng(0), car=1)
    assert steer == pytest.approx(7.0) and speed == pytest.approx(2.2)
    # noise: "none" keeps DeepRacer's noise (0.01 rad, 0.1 m/s); scale 3 triples it
    base = _draw(Randomization())
    loud = _draw(Randomization(steer_noise_scale=(3, 3), speed_noise_scale=(3, 3)))
    rng = np.random.default_rng(1)
    speeds = np.array([apply_command(0.0, 2.0, base, rng)[1] for _ in range(4000)])
    speeds3 = np.array([apply_command(0.0, 2.0, loud, rng)[1] for _ in range(4000)])
    assert speeds.std() == pytest.approx(0.1, rel=0.1) and speeds3.std() == pytest.approx(0.3, rel=0.1)
    # same seed, same commands
    a = [apply_command(1.0, 1.0, loud, np.random.default_rng(5)) for _ in range(3)]
    b = [apply_command(1.0, 1.0, loud, np.random.default_rng(5)) for _ in range(3)]
    assert a == b


def test_presets_and_flags():
    assert not Randomization.from_config(None).enabled
    assert not Randomization.preset("none").enabled
    mild = Randomization.from_config("mild")
    assert mild.perception_enabled and mild.dynamics_enabled and mild.camera_enabled
    only_noise = Randomization.from_config({"noise_sigma": [0, 5]})
    assert only_noise.perception_enabled and not only_noise.dynamics_enabled
    assert only_noise.noise_sigma == (0.0, 5.0)
    based = Randomization.from_config({"preset": "strong", "speed_gain": (1.0, 1.0)})
    assert based.speed_gain == (1.0, 1.0) and based.brightness == Randomization.preset("strong").brightness
    assert "noise_sigma" in Randomization.describe()


@pytest.mark.parametrize("config, words", [
    ({"brightnes": (0, 1)}, ["brightnes"]),
    ({"contrast": (1.3, 0.7)}, ["contrast"]),
    ({"noise_sigma": (0, 500)}, ["noise_sigma"]),
    ({"speed_gain": 1.1}, ["speed_gain", "pair"]),
    ({"blur_kernels": (4,)}, ["blur_kernels"]),
    ({"shadow_prob": 2.0}, ["shadow_prob"]),
    ({"preset": "wild"}, ["wild"]),
    ("extreme", ["extreme"]),
    (3, ["int"]),
])
def test_from_config_errors(config, words):
    with pytest.raises(ValueError) as err:
        Randomization.from_config(config)
    for word in words:
        assert word in str(err.value)
