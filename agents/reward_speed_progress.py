"""A DeepRacer reward function as community racers write them: go fast, make progress, stay on the road.

Runs unchanged on the DeepRacer console and in multirace (`multirace train --reward FILE`). It reads only
DeepRacer's reward params: `is_offtrack`, `all_wheels_on_track`, `speed` (the commanded speed, m/s),
`progress` (% of the lap), `steps`, `distance_from_center` and `track_width`.
"""

MAX_SPEED = 4.0  # m/s, the top of the action space


def reward_function(params):
    if params["is_offtrack"]:
        return 1e-3
    reward = (params["speed"] / MAX_SPEED) ** 2  # speed term: the faster the better, squared as racers do
    steps = params["steps"]
    if steps > 0:
        reward += params["progress"] / steps  # progress term: % of the lap per step, high when laps are quick
    if not params["all_wheels_on_track"]:
        reward *= 0.5  # some wheels off: legal, but risky
    if params["distance_from_center"] > 0.45 * params["track_width"]:
        reward *= 0.8  # on the edge of the road
    return float(reward)
