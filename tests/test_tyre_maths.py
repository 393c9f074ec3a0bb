"""The tyre kernel's own maths (polynomials in place of libm) against Python's `math`, and the kernel against the
model written with `math`, as `dynamics.advance` was before."""
import dataclasses
import math

import numpy as np
import pytest

from multirace.sim import dynamics
from multirace.sim.car import GRAVITY, CarSpec
from multirace.sim.world import World

PARAMS = World(CarSpec(), 1, 0, 60, 15, "dynamic")._params
STEP = 1.0 / 15


def reference_advance(u, v, r, delta, target, grip, motor, params, step_time):
    """`dynamics.advance` as it was, with libm's maths: the model the kernel must keep."""
    mass, iz, lf, lr, mu0, b_tyre, c_tyre = params[0], params[1], params[2], params[3], params[4], params[5], params[6]
    accel0, brake, top, tau, v_kin, dt_max = params[7], params[8], params[9], params[10], params[11], params[12]
    rear_grip = params[13]
    wheelbase = lf + lr
    substeps = max(1, int(math.ceil(step_time / dt_max - 1e-9)))
    dt = step_time / substeps
    mu, accel = mu0 * grip, accel0 * motor
    mu_rear = mu * rear_grip
    fz_front = mass * GRAVITY * lr / wheelbase
    fz_rear = mass * GRAVITY * lf / wheelbase
    cos_d, sin_d = math.cos(delta), math.sin(delta)
    tan_d = math.tan(delta)
    beta = math.atan(lr / wheelbase * tan_d)
    cos_beta, tan_beta = math.cos(beta), math.tan(beta)
    x, y, yaw = 0.0, 0.0, 0.0
    for _ in range(substeps):
        want = mass * (target - u) / tau
        if want > 0.0:
            limit = mass * accel * max(0.0, 1.0 - u / top)
            fx = min(want, limit)
        else:
            fx = max(want, -mass * brake)
        fx_front, fx_rear = 0.5 * fx, 0.5 * fx
        cap_f = math.sqrt(max((mu * fz_front) ** 2 - fx_front ** 2, 0.0))
        cap_r = math.sqrt(max((mu_rear * fz_rear) ** 2 - fx_rear ** 2, 0.0))
        fx_front = max(min(fx_front, mu * fz_front), -mu * fz_front)
        fx_rear = max(min(fx_rear, mu_rear * fz_rear), -mu_rear * fz_rear)
        u_safe = max(abs(u), 0.05)
        alpha_f = delta - math.atan2(v + lf * r, u_safe)
        alpha_r = -math.atan2(v - lr * r, u_safe)
        fy_front = cap_f * math.sin(c_tyre * math.atan(b_tyre * alpha_f))
        fy_rear = cap_r * math.sin(c_tyre * math.atan(b_tyre * alpha_r))
        du = (fx_front * cos_d - fy_front * sin_d + fx_rear) / mass + v * r
        dv = (fx_front * sin_d + fy_front * cos_d + fy_rear) / mass - u * r
        dr = (lf * (fx_front * sin_d + fy_front * cos_d) - lr * fy_rear) / iz
        u_dyn, v_dyn, r_dyn = u + du * dt, v + dv * dt, r + dr * dt
        speed = math.hypot(u, v)
        u_kin = u + (fx_front + fx_rear) / mass * dt
        r_kin = u_kin * cos_beta * tan_d / wheelbase
        v_kin_state = u_kin * tan_beta
        w = min(max((speed - v_kin) / v_kin, 0.0), 1.0)
        u = w * u_dyn + (1.0 - w) * u_kin
        v = w * v_dyn + (1.0 - w) * v_kin_state
        r = w * r_dyn + (1.0 - w) * r_kin
        if u < 0.0 and target >= 0.0 and speed < 0.05:
            u = 0.0
        cy, sy = math.cos(yaw), math.sin(yaw)
        x += (u * cy - v * sy) * dt
        y += (u * sy + v * cy) * dt
        yaw += r * dt
    return u, v, r, x, y, yaw


def ulps(ours, exact):
    """How many units in the last place of `exact` `ours` is off."""
    return np.abs(np.asarray(ours) - exact) / np.spacing(np.abs(exact))


def test_atan2_right_agrees_with_math_to_two_ulps():
    rng = np.random.default_rng(0)
    y = np.concatenate([rng.normal(0.0, 3.0, 20000), rng.uniform(-1.0, 1.0, 5000) * 10.0 ** rng.uniform(-9, 9, 5000)])
    x = np.concatenate([rng.uniform(0.05, 5.0, 20000), 10.0 ** rng.uniform(-3, 3, 5000)])
    y = np.concatenate([y, [0.41421356237309503, 2.414213562373095, 1.0, -1.0, 1e-300]])  # at the reductions' seams
    x = np.concatenate([x, [1.0, 1.0, 1.0, 1.0, 1.0]])
    ours = np.array([dynamics.atan2_right(a, b) for a, b in zip(y, x)])
    exact = np.array([math.atan2(a, b) for a, b in zip(y, x)])
    assert ulps(ours, exact).max() <= 2.0
    assert (np.abs(ours - exact) / np.abs(exact)).max() < 3e-16


def test_atan_agrees_with_math_over_every_magnitude():
    rng = np.random.default_rng(1)
    wide = rng.choice([-1.0, 1.0], 5000) * 10.0 ** rng.uniform(-12, 12, 5000)
    t = np.concatenate([rng.uniform(-25.0, 25.0, 20000), wide])
    ours = np.array([dynamics.atan2_right(a, 1.0) for a in t])
    exact = np.array([math.atan(a) for a in t])
    assert ulps(ours, exact).max() <= 2.0
    assert math.copysign(1.0, dynamics.atan2_right(-0.0, 1.0)) == -1.0
    assert dynamics.atan2_right(math.inf, 1.0) == math.pi / 2 and dynamics.atan2_right(-math.inf, 1.0) == -math.pi / 2


def test_sin_wide_agrees_with_math_over_three_half_turns():
    rng = np.random.default_rng(2)
    x = np.concatenate([rng.uniform(-1.5 * math.pi, 1.5 * math.pi, 30000),
                        [0.0, 1e-10, math.pi / 2, -math.pi / 2, math.pi, -math.pi, 1.5 * math.pi, -1.5 * math.pi]])
    ours = np.array([dynamics.sin_wide(a) for a in x])
    exact = np.array([math.sin(a) for a in x])
    assert np.abs(ours - exact).max() <= 2.3e-16
    nonzero = exact != 0.0
    assert ulps(ours[nonzero], exact[nonzero]).max() <= 2.0


def random_states(n, seed):
    """States and commands over the range a race covers, and spins."""
    rng = np.random.default_rng(seed)
    r = rng.normal(0.0, 2.0, n)
    r[: n // 10] = rng.choice([-15.0, 15.0], n // 10)
    return np.column_stack([rng.uniform(-0.2, 4.5, n), rng.normal(0.0, 0.3, n), r, rng.uniform(-0.52, 0.52, n),
                            rng.uniform(0.0, 4.0, n), rng.uniform(0.7, 1.3, n), rng.uniform(0.7, 1.3, n)])


def test_one_step_agrees_with_the_model_written_with_math():
    worst = np.zeros(6)
    for state in random_states(2500, seed=3):
        ours = dynamics.advance(*state, PARAMS, STEP)
        exact = reference_advance(*state, PARAMS, STEP)
        worst = np.maximum(worst, np.abs(np.subtract(ours, exact)))
    assert worst.max() < 1e-12, worst  # u, v, r, x, y, yaw: found about 1e-13 at most


@pytest.mark.parametrize("r", [-80.0, 80.0])
def test_a_spin_past_the_heading_series_takes_math_and_agrees(r):
    assert abs(r * PARAMS[12]) > dynamics.TURN_MAX
    for state in random_states(50, seed=4):
        state[2] = r
        np.testing.assert_allclose(dynamics.advance(*state, PARAMS, STEP), reference_advance(*state, PARAMS, STEP),
                                   rtol=0.0, atol=1e-12)


def test_a_tyre_curve_beyond_the_sine_range_is_refused():
    with pytest.raises(ValueError, match="tyre_c"):
        World(dataclasses.replace(CarSpec(), tyre_c=3.5), 1, 0, 60, 15, "dynamic")
