"""The uncertainty schedule: head-to-head pairings chosen where the table is unsure (close ratings, high sigma).

A league with `schedule = "uncertainty"` plays its head-to-head matches in batches. Each batch is planned
from the results of every batch before it (never from matches still running), so the same league with the
same seeds plans the same pairs whatever the machine's load or the order its workers finish in: the pairs
whose outcome is least predictable and whose ratings are least known (OpenSkill's draw probability of the
pair times the sum of their variances), each pair at most once, each entrant at most once a batch,
equal scores in an order drawn from the pair's names. A pairing plays every (track, direction, seed, trial)
block, grid order rotated as in the round robin. Planning stops at the budget (`opponents` per entrant on
average, at most everyone once) or once every entrant's sigma is at most `stop_sigma`.
"""
from __future__ import annotations

import hashlib
import itertools


def rate(model, names, heats) -> dict:
    """OpenSkill ratings of `names` after `heats`, each a list of (name, finishing position) best first, in
    the given order (as `league table` rates them)."""
    ratings = {n: model.rating(name=n) for n in names}
    for heat in heats:
        new = model.rate([[ratings[n]] for n, _ in heat], ranks=[position for _, position in heat])
        for (n, _), team in zip(heat, new):
            ratings[n] = team[0]
    return ratings


def _tie_break(pair, salt: str) -> str:
    return hashlib.sha256(f"{salt}\n{pair[0]}\n{pair[1]}".encode()).hexdigest()


def uncertain_heats(model, ratings: dict, count: int, met: set, salt: str = "") -> list[tuple[str, str]]:
    """Up to `count` disjoint pairs of entrants that have not met (`met`: frozenset pairs) for the next heats,
    most informative first; equal scores in the order of a hash of `salt` and the pair."""
    def score(pair):
        a, b = ratings[pair[0]], ratings[pair[1]]
        return model.predict_draw([[a], [b]]) * (a.sigma ** 2 + b.sigma ** 2), _tie_break(pair, salt)

    candidates = sorted((p for p in itertools.combinations(sorted(ratings), 2) if frozenset(p) not in met),
                        key=score, reverse=True)
    chosen, busy = [], set()
    for a, b in candidates:
        if a not in busy and b not in busy:
            chosen.append((a, b))
            busy |= {a, b}
            if len(chosen) == count:
                break
    return chosen


def next_pairs(model, names: list[str], heats, met: set, settings: dict) -> list[tuple[str, str]]:
    """The next batch of pairings, or [] when planning stops: `heats` are the recorded heats (for `rate`)
    in schedule order, `met` the pairs planned so far, `settings` the head_to_head table
    (`opponents`, `stop_sigma`, `batch`)."""
    if len(names) < 2:
        return []
    every_pair = len(names) * (len(names) - 1) // 2
    budget = every_pair if settings.get("opponents") is None else min(every_pair,
                                                                       settings["opponents"] * len(names) // 2)
    planned = len(met)
    ratings = rate(model, names, heats)
    if planned >= budget or (settings.get("stop_sigma") is not None and planned
                             and max(r.sigma for r in ratings.values()) <= settings["stop_sigma"]):
        return []
    batch = settings.get("batch") or len(names) // 2
    return uncertain_heats(model, ratings, min(batch, budget - planned), met)
