"""Ratings that settle fast: head-to-head heats chosen where the table is uncertain, and how to measure it.

`uncertain_heats` picks the next heats of 2 cars: pairs whose outcome is least predictable and whose ratings
are least known (OpenSkill's draw probability of the pair times the sum of their variances), each entrant at
most once per batch, pairs that met least often first. `measure` compares it with a round robin on real
races: each pairing is raced from both grid orders (bots that never overtake would otherwise lose from
behind whatever their speed); two independent chains of results (on seeds 1 and 2) are rated apart, and
the number of pairings per chain until their top 8 agree (Kendall tau >= 0.9, two batches running) is the
figure. The round robin's chains race disjoint halves of its pairings: the races of these entrants hardly
depend on the seed, so the same pairings on two seeds would agree at once. The schedule is not yet what
`league run` plays: it is measured here first.
`python -m multirace.league.convergence OUT.json` runs the measurement on 32 entrants.
"""
from __future__ import annotations

import itertools
import json
import random
import sys
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path


def uncertain_heats(model, ratings: dict, count: int, met: dict) -> list[tuple[str, str]]:
    """Up to `count` disjoint pairs of entrants for the next heats, most informative first."""
    def score(pair):
        a, b = ratings[pair[0]], ratings[pair[1]]
        return (-met.get(frozenset(pair), 0), model.predict_draw([[a], [b]]) * (a.sigma ** 2 + b.sigma ** 2))

    candidates = sorted(itertools.combinations(sorted(ratings), 2), key=score, reverse=True)
    chosen, busy = [], set()
    for a, b in candidates:
        if a not in busy and b not in busy:
            chosen.append((a, b))
            busy |= {a, b}
            if len(chosen) == count:
                break
    return chosen


def top_tau(first: list[str], second: list[str], k: int = 8) -> float:
    """Kendall tau between two rankings over the first ranking's top k (the second ranks them too)."""
    from scipy.stats import kendalltau

    top = first[:k]
    where = {name: i for i, name in enumerate(second)}
    return float(kendalltau(range(len(top)), [where[n] for n in top]).statistic)


def _ranking(model, names, heats, tie_order: dict) -> tuple[dict, list[str]]:
    """Ratings after `heats` (winner, loser) and the ranking; equal ratings in the chain's own random order,
    so that two chains never agree merely because they break ties alike."""
    ratings = {n: model.rating(name=n) for n in names}
    for winner, loser in heats:
        new = model.rate([[ratings[winner]], [ratings[loser]]], ranks=[1, 2])
        ratings[winner], ratings[loser] = new[0][0], new[1][0]
    return ratings, sorted(names, key=lambda n: (-round(ratings[n].ordinal(), 9), tie_order[n]))


def _play(task) -> tuple:
    """One real pairing of two entrants (in a worker process), raced from both grid orders on the seed (a
    car that never overtakes loses from behind whatever its speed): (a, b, seed, winner). The winner has the
    better sum of finishing positions, then the more distance over both races."""
    from .worker import run_match

    a, b, seed, specs, track, steps = task
    score = {a: [0, 0.0], b: [0, 0.0]}
    for grid in ((a, b), (b, a)):
        entrants = [{"name": n, "spec": specs[n], "sha256": None, "step_budget": 0.5} for n in grid]
        spec = {"kind": "head_to_head", "race": "head_to_head", "track": track, "reverse": False, "seed": seed,
                "trial": 0, "laps": 1, "max_steps": steps, "entrants": entrants}
        for car in run_match(spec, Path("/"), None)["cars"]:
            score[car["name"]][0] -= car["position"]
            score[car["name"]][1] += car["laps"] * 100 + (car.get("progress") or 0.0)
    return a, b, seed, max((a, b), key=lambda n: (score[n], n == min(a, b)))


class Outcomes:
    """Real heat results, cached in a JSON file (a pair on a seed is raced once)."""

    def __init__(self, path: Path, specs: dict, track: str, steps: int, workers: int):
        self.path, self.specs, self.track, self.steps = path, specs, track, steps
        self.pool = ProcessPoolExecutor(workers)
        self.known = json.loads(path.read_text()) if path.is_file() else {}

    def winners(self, heats: list[tuple[str, str, int]]) -> list[str]:
        todo = [h for h in heats if self._key(*h) not in self.known]
        tasks = [(a, b, s, self.specs, self.track, self.steps) for a, b, s in todo]
        for a, b, seed, winner in self.pool.map(_play, tasks):
            self.known[self._key(a, b, seed)] = winner
        if todo:
            self.path.write_text(json.dumps(self.known, sort_keys=True))
        return [self.known[self._key(*h)] for h in heats]

    @staticmethod
    def _key(a, b, seed) -> str:
        return f"{min(a, b)}|{max(a, b)}|{seed}"


def _chains(outcomes: Outcomes, names, schedule, batch: int):
    """Two chains of a schedule (outcomes on seeds 1 and 2), a batch of pairings each per step: yields the
    pairings per chain so far and the Kendall tau of the two chains' top 8."""
    from openskill.models import PlackettLuce

    model = PlackettLuce()
    played = {1: [], 2: []}
    ties = {seed: dict(zip(names, random.Random(seed).sample(range(len(names)), len(names)))) for seed in (1, 2)}
    while True:
        for seed in (1, 2):
            ratings, _ = _ranking(model, names, played[seed], ties[seed])
            met = {}
            for w, l in played[seed]:
                met[frozenset((w, l))] = met.get(frozenset((w, l)), 0) + 1
            pairs = schedule(model, ratings, batch, met, len(played[seed]), seed)
            winners = outcomes.winners([(a, b, seed) for a, b in pairs])
            played[seed] += [(w, b if w == a else a) for (a, b), w in zip(pairs, winners)]
        rankings = [_ranking(model, names, played[seed], ties[seed])[1] for seed in (1, 2)]
        yield len(played[1]), top_tau(*rankings)


def measure(entrants: dict, out: Path, track: str = "reinvent_base", steps: int = 100, batch: int = 16,
            workers: int = 2, seed: int = 0) -> dict:
    """Pairings per chain until two independent chains' top 8 agree (tau >= 0.9 for two batches running):
    the uncertainty schedule against a round robin in random order, a batch of each in turn (so a run
    stopped early compares them at equal cost). `entrants` maps names to agent files or bot specs."""
    names = sorted(entrants)
    order = list(itertools.combinations(names, 2))
    random.Random(seed).shuffle(order)
    halves = {1: order[0::2], 2: order[1::2]}  # a round robin's two independent halves: disjoint pairings
    schedules = {"uncertainty": lambda model, ratings, count, met, done, seed: uncertain_heats(model, ratings, count,
                                                                                              met),
                 "round_robin": lambda model, ratings, count, met, done, seed: halves[seed][done:done + count]}
    result = {"entrants": len(names), "track": track, "max_steps": steps, "batch": batch}
    outcomes = Outcomes(out.with_suffix(".heats.json"), entrants, track, steps, workers)
    chains = {key: _chains(outcomes, names, schedule, batch) for key, schedule in schedules.items()}
    for key in chains:
        result[key] = {"converged_at": None, "curve": [], "agreed": 0}
    try:
        while any(r["converged_at"] is None and len(r["curve"]) * batch < len(order) // 2
                  for r in (result[k] for k in chains)):
            for key, chain in chains.items():
                state = result[key]
                if state["converged_at"] is not None:
                    continue
                count, tau = next(chain)
                state["curve"].append({"pairings_per_chain": count, "tau_top8": round(tau, 4)})
                state["agreed"] = state["agreed"] + 1 if tau >= 0.9 else 0
                if state["agreed"] == 2:  # two batches in a row: agreement that holds, not a coincidence
                    state["converged_at"] = count - batch
                out.write_text(json.dumps({**result, "races": 2 * len(outcomes.known)}, indent=2))
    finally:
        outcomes.pool.shutdown()
    return {**result, "races": 2 * len(outcomes.known)}


def league_of_32() -> dict:
    """32 entrants: the 4 shipped agents and 28 bots of four kinds and many speeds."""
    from ..resources import agents_dir

    entrants = {p.stem: str(p) for p in sorted(agents_dir().glob("*.pt"))}
    speeds = [0.6, 0.8, 1.0, 1.2, 1.4, 1.6, 1.8, 2.0]
    bots = ([f"bot:follow@{s}" for s in speeds] + [f"bot:lanes@{s}" for s in speeds]
            + [f"bot:pass@{s}" for s in speeds[1:7]] + [f"bot:racingline@{s}" for s in (0.5, 0.6, 0.7, 0.8, 0.9, 1.0)])
    entrants.update({b: b for b in bots[:32 - len(entrants)]})
    return entrants


if __name__ == "__main__":
    print(json.dumps(measure(league_of_32(), Path(sys.argv[1])), indent=2))
