"""The car's motion: a single-track (bicycle) model with tyre forces and a drive train with limits.

One compiled kernel (`drive`) advances every car over one action step, in
substeps of `DynamicsParams.dt` seconds. State per car, in its own frame: forward speed
`u`, sideways speed `v` (+ left) and yaw rate `r`. The model:

- Drive train: the commanded speed is a target; the longitudinal force that
  chases it is limited to the motor's acceleration (`accel`, lower at speed:
  the force falls linearly to zero at `top_speed`) and the brakes'
  deceleration (`brake`), and is shared by all four wheels (4WD).
- Tyres: each axle's lateral force is a saturating curve of its slip angle,
  ``mu Fz sin(C atan(B alpha))`` (Pacejka's shape), reduced by the
  longitudinal force the axle carries (friction circle): past the grip limit
  the car slides, its path radius grows and it can spin. The rear tyres grip
  a little more than the front ones (`rear_grip`), so past the limit the car
  slides wide (understeer) rather than spinning, as a set-up RC car does.
- Yaw: ``Iz r' = lf Fyf cos(delta) - lr Fyr``.
- Below `kinematic_speed` the tyre model is ill-conditioned (slip angles of a
  barely moving car), so the motion blends to the kinematic bicycle
  (no slip) between `kinematic_speed` and twice that speed.

`advance` returns a car's new state and its displacement over the step
(forward, left, yaw in the car's frame at the start), which `drive` turns
into the body velocity PyBullet integrates; PyBullet owns the contacts, and
whatever a contact adds to a body's velocity is fed back into the state.

Speed: the cars run side by side, `LANES` to a block, and each substep is
arithmetic that LLVM vectorises across a block's lanes (one AVX2 register
holds four cars' values). For that the maths in the substeps is our own
polynomial approximations rather than libm calls, which do not vectorise:
`atan2_right` (atan2 for x > 0, and atan) and `sin_wide` (sin for
|x| <= 3 pi/2) agree with `math` to 2 units in the last place (relative
error below 3e-16), and the heading is carried from substep to substep by a
rotation whose cos and sin are Taylor series of the small angle turned
(error below 3e-19; a car turning more than `TURN_MAX` rad in a substep gets
`math.cos` / `math.sin` of its heading instead). One step agrees with the
model written with `math` (as it was before) to about 1e-13 in every output.
"""
from __future__ import annotations

import dataclasses
import math

import numba
import numpy as np

from .car import GRAVITY

# numpy's error model: a float division does not check for zero (a check would keep LLVM from vectorising).
# No fastmath, not even "contract" (fused multiply-adds): which products LLVM fuses depends on what it inlines,
# and a caller compiled in the same process inlines these kernels where one loaded from numba's cache cannot,
# so with it the first race after an install rounded differently from every later one (same seeds, another race).
_KERNEL = dict(cache=True, error_model="numpy")
# inlined into the kernels (cached with them) and never dispatched in a race: not cached themselves, or their cache
# index would never appear and the first-compile notice (environment/kernels.py) would show on every run
_INLINE = dict(_KERNEL, cache=False, inline="always")

# ------------------------------------------------------------------ maths

_TAN_PI_8 = 0.41421356237309503  # tan(pi/8) = sqrt(2) - 1
_TAN_3PI_8 = 2.414213562373095  # tan(3 pi/8) = sqrt(2) + 1
# pi/4, pi/2 and pi as the double nearest (hi) plus the rest (lo)
_PI_4_HI, _PI_4_LO = 0.7853981633974483, 3.061616997868383e-17
_PI_2_HI, _PI_2_LO = 1.5707963267948966, 6.123233995736766e-17
_PI_HI, _PI_LO = 3.141592653589793, 1.2246467991473532e-16

# atan(z) = z + z^3 P(z^2) on |z| <= tan(pi/8): P of degree 9 (an odd polynomial of degree 21), our minimax fit
# for relative error (Remez exchange in mpmath at 50 digits); with its coefficients rounded to doubles as here, the
# fit's relative error is below 3.6e-17, a third of the doubles' rounding.
_ATAN = (-0.3333333333333015, 0.1999999999908897, -0.14285714195262333, 0.11111106653625397, -0.09090782413279755,
         0.07690068310973684, -0.06641121272046692, 0.05692539355943635, -0.04359096145273688, 0.021259853456720067)
# sin(a) = a + a^3 Q(a^2) on |a| <= pi/2: Q of degree 7 (odd, degree 17), fitted the same way; error below 5.3e-18.
_SIN = (-0.16666666666666666, 0.008333333333333194, -0.00019841269841209218, 2.75573192111373e-06,
        -2.505210687280418e-08, 1.605893970598352e-10, -7.642991491363718e-13, 2.721174982476455e-15)
TURN_MAX = 0.1  # rad per substep: up to here the heading turns by `_turned`'s series


@numba.njit(**_INLINE)
def _atan_series(z, lo):
    """atan(z) + lo for |z| <= tan(pi/8) and a small lo, by `_ATAN` in Estrin's scheme (a short dependency
    chain)."""
    s = z * z
    s2 = s * s
    s4 = s2 * s2
    c = _ATAN
    p = (((c[0] + c[1] * s) + (c[2] + c[3] * s) * s2) + ((c[4] + c[5] * s) + (c[6] + c[7] * s) * s2) * s4
         + (c[8] + c[9] * s) * (s4 * s4))
    return (z + lo) + z * s * p


@numba.njit(**_INLINE)
def _sin_series(a):
    """sin(a) for |a| <= pi/2, by `_SIN` in Estrin's scheme."""
    s = a * a
    s2 = s * s
    c = _SIN
    p = ((c[0] + c[1] * s) + (c[2] + c[3] * s) * s2) + ((c[4] + c[5] * s) + (c[6] + c[7] * s) * s2) * (s2 * s2)
    return a + a * s * p


@numba.njit(**_INLINE)
def atan2_right(y, x):
    """atan2(y, x) for x > 0 (so atan(y) is atan2_right(y, 1.0)). With t = |y| / x, one division brings the
    argument within tan(pi/8): atan(t) = pi/4 + atan((t - 1) / (t + 1)) for t in (tan(pi/8), tan(3 pi/8)] and
    atan(t) = pi/2 - atan(1 / t) beyond."""
    t = abs(y)
    if t > _TAN_3PI_8 * x:
        num, den, hi, lo = -x, t, _PI_2_HI, _PI_2_LO
    elif t > _TAN_PI_8 * x:
        num, den, hi, lo = t - x, t + x, _PI_4_HI, _PI_4_LO
    else:
        num, den, hi, lo = t, x, 0.0, 0.0
    return math.copysign(hi + _atan_series(num / den, lo), y)


@numba.njit(**_INLINE)
def sin_wide(x):
    """sin(x) for |x| <= 3 pi/2: sin(x) = sin(pi - x) = sin(-pi - x) brings |x| > pi/2 within pi/2 (pi - x is
    exact there; pi's low part is added after)."""
    if x > _PI_2_HI:
        x = (_PI_HI - x) + _PI_LO
    elif x < -_PI_2_HI:
        x = (-_PI_HI - x) - _PI_LO
    return _sin_series(x)


@numba.njit(**_INLINE)
def _turned(cos_a, sin_a, h):
    """(cos, sin) of the angle a + h for |h| <= TURN_MAX: a rotation by h, with cos h and sin h by their Taylor
    series through h^10 and h^9 (remainders below 2.1e-21 and 2.6e-19)."""
    q = h * h
    cos_h = 1.0 + q * (-1.0 / 2 + q * (1.0 / 24 + q * (-1.0 / 720 + q * (1.0 / 40320 - q * (1.0 / 3628800)))))
    sin_h = h + h * q * (-1.0 / 6 + q * (1.0 / 120 + q * (-1.0 / 5040 + q * (1.0 / 362880))))
    return cos_a * cos_h - sin_a * sin_h, sin_a * cos_h + cos_a * sin_h


# ------------------------------------------------------------------ the model


@dataclasses.dataclass(frozen=True)
class DynamicsParams:
    """The numbers the kernel needs, from a `CarSpec` (see there for where each comes from)."""

    mass: float
    yaw_inertia: float
    front_axle: float  # lf: centre of mass to the front axle, m
    rear_axle: float  # lr
    mu: float
    rear_grip: float  # the rear tyres' friction over the front's
    tyre_b: float
    tyre_c: float  # |C| <= 3: `sin_wide` covers C atan(..) up to 3 pi/2
    accel: float
    brake: float
    top_speed: float
    drive_time_constant: float
    kinematic_speed: float
    dt: float

    def __post_init__(self):
        if abs(self.tyre_c) > 3.0:
            raise ValueError(f"tyre_c: {self.tyre_c} puts C atan(..) past the 3 pi/2 the tyre curve's sin covers")

    def as_array(self) -> np.ndarray:
        return np.array([self.mass, self.yaw_inertia, self.front_axle, self.rear_axle, self.mu, self.tyre_b,
                         self.tyre_c, self.accel, self.brake, self.top_speed, self.drive_time_constant,
                         self.kinematic_speed, self.dt, self.rear_grip])


LANES = 4  # cars per block, advanced side by side
# A block holds each field for its LANES cars side by side: field f of lane l at f * LANES + l. The offsets are
# unsigned so that numba adds no negative-index wrap-around, which would hide the layout from LLVM's vectoriser.
(_U, _V, _R, _X, _Y, _YAW, _COS_YAW, _SIN_YAW,  # state; displacement and heading since the step's start
 _STEER, _COS_STEER, _SIN_STEER, _TARGET, _HOLD,  # command; _HOLD 1.0 if the brakes may hold the car
 _GRIP_FRONT, _GRIP_REAR, _MOTOR,  # friction limits mu Fz (N) and the motor's force at rest (N)
 _KIN_V, _KIN_R,  # kinematic bicycle: v and r per unit u
 _COS_HEADING, _SIN_HEADING) = (np.uint64(f * LANES) for f in range(20))  # `drive`'s: the heading in the world
_BLOCK = np.uint64(20 * LANES)


@numba.njit(**_INLINE)
def _slot(j):
    """Where car `j` of a set of blocks starts."""
    return np.uint64(j // LANES) * _BLOCK + np.uint64(j % LANES)


@numba.njit(**_INLINE)
def _load(block, k, u, v, r, delta, target, grip, motor, params):
    """Put a car's state and what its command and randomisation set for the whole step at `k` in `block`."""
    mass, lf, lr, mu0, accel, rear_grip = params[0], params[2], params[3], params[4], params[7], params[13]
    wheelbase = lf + lr
    mu = mu0 * grip
    block[k + _U], block[k + _V], block[k + _R] = u, v, r
    block[k + _COS_YAW] = 1.0
    block[k + _STEER], block[k + _TARGET] = delta, target
    block[k + _HOLD] = 1.0 if target >= 0.0 else 0.0
    cos_d, sin_d = math.cos(delta), math.sin(delta)
    block[k + _COS_STEER], block[k + _SIN_STEER] = cos_d, sin_d
    block[k + _GRIP_FRONT] = mu * (mass * GRAVITY * lr / wheelbase)
    block[k + _GRIP_REAR] = mu * rear_grip * (mass * GRAVITY * lf / wheelbase)
    block[k + _MOTOR] = mass * (accel * motor)
    # kinematic bicycle: slip angle beta = atan(lr / wheelbase tan(delta)), v = u tan(beta),
    # r = u cos(beta) tan(delta) / wheelbase
    tan_d = sin_d / cos_d
    tan_beta = lr / wheelbase * tan_d
    block[k + _KIN_V] = tan_beta
    block[k + _KIN_R] = tan_d / (wheelbase * math.sqrt(1.0 + tan_beta * tan_beta))


@numba.njit(**_INLINE)
def _model(params, dt):
    """What every car's substep of `dt` seconds needs from `params`, as a tuple of numbers (divisions done)."""
    mass, iz, lf, lr, b_tyre, c_tyre = params[0], params[1], params[2], params[3], params[5], params[6]
    brake, top, tau, v_kin = params[8], params[9], params[10], params[11]
    return (1.0 / mass, 1.0 / iz, lf, lr, b_tyre, c_tyre, mass / tau, mass * brake, 1.0 / top, v_kin, 1.0 / v_kin,
            dt)


@numba.njit(**_INLINE)
def _car(block, k):
    """What the command and the randomisation set for the car at `k` in `block`, for `_substep`."""
    return (block[k + _STEER], block[k + _COS_STEER], block[k + _SIN_STEER], block[k + _TARGET], block[k + _HOLD],
            block[k + _GRIP_FRONT], block[k + _GRIP_REAR], block[k + _MOTOR], block[k + _KIN_V], block[k + _KIN_R])


@numba.njit(**_INLINE)
def _substep(u, v, r, car, model):
    """A car's state (u, v, r) after one substep, under what `_car` and `_model` say."""
    delta, cos_d, sin_d, target, hold, grip_f, grip_r, motor, kin_v, kin_r = car
    inv_mass, inv_iz, lf, lr, b_tyre, c_tyre, gain, brake_force, inv_top, v_kin, inv_v_kin, dt = model
    # drive train: chase the target speed within the motor's and the brakes' limits
    want = gain * (target - u)
    limit = motor * max(0.0, 1.0 - u * inv_top)
    fx = max(min(want, limit), -brake_force)  # limit >= 0: a positive want is capped, a negative one braked
    # tyres: saturating lateral force, reduced by the longitudinal force (friction circle)
    fx_half = 0.5 * fx
    cap_f = math.sqrt(max(grip_f * grip_f - fx_half * fx_half, 0.0))
    cap_r = math.sqrt(max(grip_r * grip_r - fx_half * fx_half, 0.0))
    fx_front = max(min(fx_half, grip_f), -grip_f)
    fx_rear = max(min(fx_half, grip_r), -grip_r)
    u_safe = max(abs(u), 0.05)
    alpha_f = delta - atan2_right(v + lf * r, u_safe)
    alpha_r = -atan2_right(v - lr * r, u_safe)
    fy_front = cap_f * sin_wide(c_tyre * atan2_right(b_tyre * alpha_f, 1.0))
    fy_rear = cap_r * sin_wide(c_tyre * atan2_right(b_tyre * alpha_r, 1.0))
    lateral_f = fx_front * sin_d + fy_front * cos_d
    du = (fx_front * cos_d - fy_front * sin_d + fx_rear) * inv_mass + v * r
    dv = (lateral_f + fy_rear) * inv_mass - u * r
    dr = (lf * lateral_f - lr * fy_rear) * inv_iz
    # kinematic bicycle at walking pace: no slip, yaw rate from the steering geometry
    speed = math.sqrt(u * u + v * v)
    u_kin = u + (fx_front + fx_rear) * inv_mass * dt
    w = min(max((speed - v_kin) * inv_v_kin, 0.0), 1.0)  # 0: kinematic .. 1: dynamic
    u_new = w * (u + du * dt) + (1.0 - w) * u_kin
    v_new = w * (v + dv * dt) + (1.0 - w) * (u_kin * kin_v)
    r_new = w * (r + dr * dt) + (1.0 - w) * (u_kin * kin_r)
    if u_new < 0.0 and hold > 0.0 and speed < 0.05:  # brakes hold a stopped car; no reversing
        u_new = 0.0
    return u_new, v_new, r_new


@numba.njit(**_KERNEL)
def _run(block, blocks, params, step_time):
    """Advance the first `blocks` blocks of cars in `block` over `step_time` seconds."""
    substeps = max(1, int(math.ceil(step_time / params[12] - 1e-9)))
    dt = step_time / substeps
    model = _model(params, dt)
    end = np.uint64(blocks) * _BLOCK
    for _ in range(substeps):
        for start in range(np.uint64(0), end, _BLOCK):
            # Vectorised across the lanes, in this shape only: the loads first (`_car`), arithmetic on plain numbers
            # (`_substep`), the stores last. Loads or stores among the branches of inlined code stop LLVM.
            for lane in range(np.uint64(LANES)):
                k = start + lane
                u, v, r = _substep(block[k + _U], block[k + _V], block[k + _R], _car(block, k), model)
                cos_y, sin_y = block[k + _COS_YAW], block[k + _SIN_YAW]
                block[k + _U], block[k + _V], block[k + _R] = u, v, r
                # the pose in the starting frame
                block[k + _X] += (u * cos_y - v * sin_y) * dt
                block[k + _Y] += (u * sin_y + v * cos_y) * dt
                block[k + _YAW] += r * dt
                block[k + _COS_YAW], block[k + _SIN_YAW] = _turned(cos_y, sin_y, r * dt)
        for start in range(np.uint64(0), end, _BLOCK):
            for k in range(start, start + np.uint64(LANES)):
                if abs(block[k + _R] * dt) > TURN_MAX:  # turning too fast for the series: the heading afresh
                    block[k + _COS_YAW] = math.cos(block[k + _YAW])
                    block[k + _SIN_YAW] = math.sin(block[k + _YAW])


@numba.njit(**dict(_KERNEL, cache=False))  # one car, for tests and tools; a race runs `drive` (cached)
def advance(u, v, r, delta, target, grip, motor, params, step_time):
    """Advance one car over `step_time` seconds from its state (u, v, r) under its command (steer `delta` rad,
    `target` speed m/s); grip and motor scale its friction and motor force (randomisation; 1.0 nominal).
    Returns (u, v, r, x, y, yaw): its new state and its displacement (forward m, left m, yaw rad) in its
    starting frame."""
    block = np.zeros(int(_BLOCK))
    _load(block, np.uint64(0), u, v, r, delta, target, grip, motor, params)
    _run(block, 1, params, step_time)
    return block[_U], block[_V], block[_R], block[_X], block[_Y], block[_YAW]


@numba.njit(**_KERNEL)
def drive(poses, motion, velocity, rows, pushes, commands, grip, motor, params, step_time):
    """Advance the cars `rows` over one action step and set the world velocities that carry them there.

    poses (n, 3) of (x, y, yaw); motion (n, 3) of (u, v, r), updated in place after adding each car's push
    (pushes (n, 3): x, y, yaw rate in the world frame, what contacts added since the last step); commands (n, 2)
    of (steer rad, target speed m/s); velocity (n, 3) receives (x, y, yaw rate) in the world frame: the step's
    displacement over its time.
    """
    blocks = (rows.shape[0] + LANES - 1) // LANES
    block = np.zeros(blocks * int(_BLOCK))
    for j in range(rows.shape[0]):
        i, k = rows[j], _slot(j)
        cos_y, sin_y = math.cos(poses[i, 2]), math.sin(poses[i, 2])
        push_x, push_y = pushes[i, 0], pushes[i, 1]
        _load(block, k, motion[i, 0] + (push_x * cos_y + push_y * sin_y),
              motion[i, 1] + (-push_x * sin_y + push_y * cos_y), motion[i, 2] + pushes[i, 2],
              commands[i, 0], commands[i, 1], grip[i], motor[i], params)
        block[k + _COS_HEADING], block[k + _SIN_HEADING] = cos_y, sin_y
    _run(block, blocks, params, step_time)
    for j in range(rows.shape[0]):
        i, k = rows[j], _slot(j)
        cos_y, sin_y = block[k + _COS_HEADING], block[k + _SIN_HEADING]
        motion[i, 0], motion[i, 1], motion[i, 2] = block[k + _U], block[k + _V], block[k + _R]
        forward, left = block[k + _X] / step_time, block[k + _Y] / step_time
        velocity[i, 0] = forward * cos_y - left * sin_y
        velocity[i, 1] = forward * sin_y + left * cos_y
        velocity[i, 2] = block[k + _YAW] / step_time
