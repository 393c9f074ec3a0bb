"""The top-down race view: `render_mode="rgb_array"` frames for people and videos.

``render_topdown(env, size=(540, 960)) -> uint8 RGB (H, W, 3)``: the whole
track (the env's top-down texture, downscaled once per env and size) on the
left, cars as oriented rectangles in their `CAR_COLOURS` with a white heading
mark and a short trail (the last `TRAIL_SECONDS` of positions), the boxes, and
a panel on the right: race time and, per car in the order the race stands
(`panel_order`: penalties counted, the result's order once the race is over),
position, name, lap k/N, status, penalty seconds, resets and at-fault collisions. A car that is
penalised or put back is ringed in white for `MARK_SECONDS` with what it got
("+5s", "reset"). Parked cars (finished or forfeited runs) are not drawn.

What the view keeps per env (the scaled background, the trails, the marks) is
its own `view_state(env)`, held in this module while the env lives; a new
episode (the env's step counter going back) clears the trails.
"""
from __future__ import annotations

import collections
import math
import weakref

import cv2
import numpy as np

from ..sim.world import CAR_COLOURS, OBSTACLE_COLOUR, OBSTACLE_SIZE

DEFAULT_SIZE = (540, 960)  # (height, width) pixels
TRAIL_SECONDS = 2.0
PANEL_COLOUR = (24, 24, 28)
TEXT_COLOUR = (235, 235, 235)
DIM_TEXT = (150, 150, 150)
OUTLINE = (10, 10, 10)
FONT = cv2.FONT_HERSHEY_SIMPLEX
CROP_MARGIN = 0.4  # metres of floor shown around the track
MIN_CAR_PIXELS = 9.0  # cars are drawn at least this long so they stay visible on small frames
MARK_SECONDS = 2.0  # how long a penalty or reset mark stays on the car
MARK_COLOUR = (255, 255, 255)  # white on a black outline: no car's colour


class _State:
    """What the view keeps between frames of one env."""

    def __init__(self):
        self.layouts: dict = {}  # (texture id, size) -> _Layout
        self.trails: list[collections.deque] = []
        self.last_step = -1
        self.seen: list[tuple[float, int]] = []  # per car: (penalty seconds, resets) at the last frame
        self.marks: list[tuple[float, str] | None] = []  # per car: (sim time the mark ends, its text)


class _Layout:
    """Where the track goes in a frame of a given size, and its scaled image."""

    def __init__(self, texture, size, bounds=None):
        height, width = size
        panel = int(np.clip(width * 0.26, 110, 300))
        track_w = max(width - panel, 1)
        tex_h, tex_w = texture.rgb.shape[:2]
        # crop the texture to the track's bounds plus a small margin
        c_lo, r_lo, c_hi, r_hi = 0, 0, tex_w, tex_h
        if bounds is not None:
            lo, hi = np.asarray(bounds[0], float)[:2], np.asarray(bounds[1], float)[:2]
            corners = texture.world_to_pixel(np.array([[lo[0] - CROP_MARGIN, hi[1] + CROP_MARGIN],
                                                       [hi[0] + CROP_MARGIN, lo[1] - CROP_MARGIN]]))
            c_lo, r_lo = (max(0, int(v)) for v in np.floor(corners[0]))
            c_hi, r_hi = min(tex_w, int(np.ceil(corners[1][0]))), min(tex_h, int(np.ceil(corners[1][1])))
        crop = texture.rgb[r_lo:r_hi, c_lo:c_hi]
        crop_h, crop_w = crop.shape[:2]
        self.scale = min(height / crop_h, track_w / crop_w)  # frame pixels per texture pixel
        new_w, new_h = max(1, int(round(crop_w * self.scale))), max(1, int(round(crop_h * self.scale)))
        corner = ((track_w - new_w) // 2, (height - new_h) // 2)  # (col, row) of the crop's corner
        # frame = texture pixel * scale + offset
        self.offset = (corner[0] - c_lo * self.scale, corner[1] - r_lo * self.scale)
        self.panel_x = track_w
        background = np.empty((height, width, 3), np.uint8)
        background[:, :track_w] = texture.palette.floor
        background[:, track_w:] = PANEL_COLOUR
        scaled = cv2.resize(crop, (new_w, new_h), interpolation=cv2.INTER_AREA)
        background[corner[1]:corner[1] + new_h, corner[0]:corner[0] + new_w] = scaled
        self.background = background
        self.texture = texture
        self.pixels_per_metre = texture.ppm * self.scale

    def to_frame(self, xy) -> np.ndarray:
        """World (x, y) -> frame (col, row), float."""
        return self.texture.world_to_pixel(xy) * self.scale + np.asarray(self.offset, dtype=np.float64)


_VIEW_STATES: "weakref.WeakKeyDictionary[object, _State]" = weakref.WeakKeyDictionary()


def view_state(env) -> _State:
    """What the view keeps between frames of `env` (an env or a replay's scene): layouts, trails, marks."""
    state = _VIEW_STATES.get(env)
    if state is None:
        state = _VIEW_STATES[env] = _State()
    return state


def layout_for(env, size=DEFAULT_SIZE) -> _Layout:
    """The (cached) layout of `env`'s track in a frame of `size` = (height, width)."""
    state = view_state(env)
    texture = env.texture
    key = (id(texture), tuple(size))
    layout = state.layouts.get(key)
    if layout is None or layout.texture is not texture:
        layout = _Layout(texture, tuple(size), getattr(env.track, "bounds", None))
        state.layouts[key] = layout
    return layout


def _box_points(layout: _Layout, x, y, yaw, length, width) -> np.ndarray:
    c, s = math.cos(yaw), math.sin(yaw)
    hl, hw = length / 2, width / 2
    local = [(hl, hw), (hl, -hw), (-hl, -hw), (-hl, hw)]
    world = np.array([(x + c * a - s * b, y + s * a + c * b) for a, b in local])
    return layout.to_frame(world)


def _fixed(points: np.ndarray) -> np.ndarray:
    return np.round(points * 16).astype(np.int32)  # 4 bits of sub-pixel precision


def _update_trails(env, state: _State) -> None:
    n = env.world.num_cars
    keep = max(2, int(round(TRAIL_SECONDS / getattr(env, "dt", 1 / 15))) + 1)
    steps = getattr(env, "steps", 0)
    if len(state.trails) != n or steps < state.last_step:
        state.trails = [collections.deque(maxlen=keep) for _ in range(n)]
    if steps != state.last_step:
        for i in range(n):
            if env.world.parked[i]:
                state.trails[i].clear()
            else:
                state.trails[i].append(tuple(env.world.poses[i][:2]))
    state.last_step = steps


def _update_marks(env, state: _State) -> None:
    """Start a mark on every car whose penalties or resets went up since the last frame."""
    now = float(getattr(env, "sim_time", 0.0))
    counts = [(float(getattr(race, "penalty_time", 0.0)), int(getattr(race, "resets", 0))) for race in env.races]
    if len(state.seen) != len(counts) or any(c < s for c, s in zip(counts, state.seen)):  # a new episode
        state.seen, state.marks = counts, [None] * len(counts)
    for i, ((penalty, resets), (seen_penalty, seen_resets)) in enumerate(zip(counts, state.seen)):
        if penalty > seen_penalty:
            state.marks[i] = (now + MARK_SECONDS, f"+{penalty - seen_penalty:g}s")
        elif resets > seen_resets:
            state.marks[i] = (now + MARK_SECONDS, "reset")
        if state.marks[i] is not None and now > state.marks[i][0]:
            state.marks[i] = None
    state.seen = counts


def panel_order(env) -> list[int]:
    """Car indices in the order the panel lists them: the race's standings with penalties counted
    (`env.standings()`, the result's order once the race is over); a stand-in without standings (a replay's
    scene) gives its recorded ranks."""
    positions = env.standings() if hasattr(env, "standings") else env.ranks()
    return sorted(range(len(positions)), key=lambda k: positions[k])


def render_topdown(env, size=DEFAULT_SIZE) -> np.ndarray:
    """The top-down race view of `env` now: uint8 RGB (height, width, 3); `size` is (height, width)."""
    height, width = (int(v) for v in size)
    if height < 32 or width < 64:
        raise ValueError(f"render_topdown: size {size!r} too small (need at least 32x64)")
    state = view_state(env)
    layout = layout_for(env, (height, width))
    frame = layout.background.copy()
    world = env.world
    started = bool(getattr(env, "races", None))
    if started:
        _update_trails(env, state)
        _update_marks(env, state)
    ppm = layout.pixels_per_metre
    spec = env.car_spec
    grow = max(1.0, MIN_CAR_PIXELS / max(spec.length * ppm, 1e-9))

    # boxes
    for x, y, yaw in world.obstacle_poses:
        pts = _fixed(_box_points(layout, x, y, yaw, OBSTACLE_SIZE[0] * grow, OBSTACLE_SIZE[1] * grow))
        cv2.fillPoly(frame, [pts], OBSTACLE_COLOUR, cv2.LINE_AA, shift=4)
        cv2.polylines(frame, [pts], True, OUTLINE, 1, cv2.LINE_AA, shift=4)

    if started:
        # trails under the cars
        thick = max(2, int(round(ppm * spec.width * 0.3)))
        for i, trail in enumerate(state.trails):
            if len(trail) >= 2 and not world.parked[i]:
                pts = _fixed(layout.to_frame(np.array(trail)))
                colour = tuple(int(c * 0.8) for c in CAR_COLOURS[i % len(CAR_COLOURS)])
                cv2.polylines(frame, [pts], False, colour, thick, cv2.LINE_AA, shift=4)
        # cars
        for i in range(world.num_cars):
            if world.parked[i]:
                continue
            x, y, yaw = world.poses[i]
            colour = CAR_COLOURS[i % len(CAR_COLOURS)]
            length, width = spec.length * grow, spec.width * grow
            body = _fixed(_box_points(layout, x, y, yaw, length, width))
            cv2.fillPoly(frame, [body], colour, cv2.LINE_AA, shift=4)
            cv2.polylines(frame, [body], True, OUTLINE, 1, cv2.LINE_AA, shift=4)
            # heading mark: a white triangle on the front third
            c, s = math.cos(yaw), math.sin(yaw)
            tip = (x + c * length * 0.5, y + s * length * 0.5)
            back = length * 0.12
            left = (x + c * back - s * width * 0.35, y + s * back + c * width * 0.35)
            right = (x + c * back + s * width * 0.35, y + s * back - c * width * 0.35)
            mark = _fixed(layout.to_frame(np.array([tip, left, right])))
            cv2.fillPoly(frame, [mark], (255, 255, 255), cv2.LINE_AA, shift=4)
            if state.marks[i] is not None:  # just penalised or put back: a ring and what it got
                centre = layout.to_frame(np.array([[x, y]]))[0]
                radius = max(6, int(round(length * ppm * 0.8)))
                col, row = int(round(centre[0])), int(round(centre[1]))
                for colour, width in ((OUTLINE, 4), (MARK_COLOUR, 2)):
                    cv2.circle(frame, (col, row), radius, colour, width, cv2.LINE_AA)
                    cv2.putText(frame, state.marks[i][1], (col + radius, row - radius), FONT, 0.5, colour,
                                width - 1, cv2.LINE_AA)

    _draw_panel(env, frame, layout, started)
    return frame


def _status_text(race, laps_total: int) -> str:
    """A car's second panel line: lap k/N, status, and its penalty seconds, resets and at-fault collisions if any
    (a replay's stand-in race holds the at-fault count as `at_fault`)."""
    lap = min(race.laps + (1 if race.racing else 0), laps_total) if laps_total else race.laps
    lap_text = f"lap {lap}/{laps_total}" if laps_total else f"lap {lap}"
    status = (race.status if race.status != "not_finished" else "unfinished").replace("_", " ")
    penalty, resets = float(getattr(race, "penalty_time", 0.0)), int(getattr(race, "resets", 0))
    faults = race.collisions_caused() if hasattr(race, "collisions_caused") else int(getattr(race, "at_fault", 0))
    marks = (f" +{penalty:g}s" if penalty else "") + (f" {resets} reset{'s' if resets > 1 else ''}" if resets else "")
    marks += f" {faults} at fault" if faults else ""
    return f"{lap_text} {status}{marks}"


def _fit(text: str, max_width: int, font: float) -> str:
    """`text`, shortened with '~' so it is at most `max_width` pixels wide."""
    while len(text) > 2 and cv2.getTextSize(text, FONT, font, 1)[0][0] > max_width:
        text = text[:-2] + "~"
    return text


def _draw_panel(env, frame: np.ndarray, layout: _Layout, started: bool) -> None:
    height, width = frame.shape[:2]
    x0 = layout.panel_x + 8
    panel_w = width - x0 - 4
    if panel_w < 40:
        return
    n = env.world.num_cars
    line = int(np.clip((height - 8) / (2 * n + 2.4), 8, 28))  # two text lines per car
    font = line / 40.0
    thick = 1
    y = line
    sim_time = float(getattr(env, "sim_time", 0.0))
    cv2.putText(frame, f"time {sim_time:6.1f} s", (x0, y), FONT, font * 1.1, TEXT_COLOUR, thick, cv2.LINE_AA)
    y += int(line * 1.4)
    if not started:
        cv2.putText(frame, "not started", (x0, y), FONT, font, DIM_TEXT, thick, cv2.LINE_AA)
        return
    laps_total = int(getattr(env.rules, "laps", 0) or 0)
    for place, i in enumerate(panel_order(env), start=1):
        race = env.races[i]
        colour = CAR_COLOURS[i % len(CAR_COLOURS)]
        sw = int(line * 0.6)
        cv2.rectangle(frame, (x0, y - sw), (x0 + sw, y), colour, -1)
        text = _fit(f"{place}. {env.car_names[i]}", panel_w - sw - 6, font)
        cv2.putText(frame, text, (x0 + sw + 6, y), FONT, font, TEXT_COLOUR, thick, cv2.LINE_AA)
        y += line
        text_colour = TEXT_COLOUR if race.racing else DIM_TEXT
        cv2.putText(frame, _fit(_status_text(race, laps_total), panel_w - sw - 6, font * 0.9), (x0 + sw + 6, y),
                    FONT, font * 0.9, text_colour, thick, cv2.LINE_AA)
        y += line
