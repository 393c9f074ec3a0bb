"""How fast the uncertainty schedule settles the table, against a round robin, on real races.

`python -m multirace.league.convergence OUT.json` measures it on 32 entrants (the shipped agents and bots
of four kinds at many speeds). Each pairing is a 1-lap heat raced from both grid orders (bots that never
overtake would otherwise lose from behind whatever their speed); the winner has the better sum of places,
then the more distance. The races hardly depend on the seed, so the measure is agreement with a reference,
not between two halves of the results:

- The reference is every pairing raced on seeds 1 and 2 (the full round robin, twice). Entrants it cannot
  order, those that beat each other round a cycle or split their two races, are tied; it orders every
  other pair (the strongly connected groups of its who-beat-whom graph, in their one order).
- A chain plays one schedule on one seed's outcomes, a batch of pairings at a time, and ranks the entrants
  by OpenSkill ordinal as `league table` does. Its agreement is Kendall's tau between its top 8 and the
  reference, over the pairs of that top 8 the reference orders. The figures are the pairings until
  tau >= 0.9 for two batches running, and until it stays there; chains differ in seed and in the order of
  equal choices (the round robin's in its random order).

Why not two independent halves: with outcomes this repeatable, two halves are independent only if they race
disjoint pairings, and then the race that orders two neighbours of the table (they beat everyone else
alike) is in one half only; the other half orders them by a coin flip. Over the 7 neighbours of a top 8
that is about 3.5 discordant pairs (tau about 0.75) whatever the schedule: the first measurement ended at
0.64-0.71. Two chains on the same pairings instead agree at once, telling nothing.
"""
from __future__ import annotations

import hashlib
import itertools
import json
import random
import statistics
import sys
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

from .uncertainty import rate, uncertain_heats

SEEDS = (1, 2)
TARGET = 0.9
CHECKPOINTS = (48, 96, 144, 192, 240, 288, 336, 400, 448, 496)  # pairings at which the curves are reported


def top_tau(table: list[str], rank: dict, k: int = 8) -> float:
    """Kendall tau between the table's top k and a reference `rank` (lower is better; equal ranks are ties,
    left out): (concordant - discordant) / the pairs the reference orders."""
    concordant = discordant = 0
    for x, y in itertools.combinations(table[:k], 2):
        concordant += rank[x] < rank[y]
        discordant += rank[x] > rank[y]
    return (concordant - discordant) / (concordant + discordant) if concordant + discordant else 1.0


def reference_rank(names: list[str], winner) -> dict:
    """Each entrant's rank in the full round robin (`winner(a, b, seed)` on every seed): the number of
    entrants above it, entrants in one strongly connected group of who-beat-whom (a cycle, or a split) tied."""
    reach = {a: {b for b in names if b != a and any(winner(a, b, s) == a for s in SEEDS)} for a in names}
    for middle in names:  # transitive closure (Warshall)
        for a in names:
            if middle in reach[a]:
                reach[a] |= reach[middle] - {a}
    return {a: sum(1 for b in names if a in reach[b] and b not in reach[a]) for a in names}


def _play(task) -> tuple:
    """One real pairing of two entrants (in a worker process), raced from both grid orders on the seed (a
    car that never overtakes loses from behind whatever its speed): (a, b, seed, winner). The winner has the
    better sum of finishing positions, then the more distance over both races."""
    from .worker import run_match

    a, b, seed, specs, track, steps = task
    score = {a: [0, 0.0], b: [0, 0.0]}
    for grid in ((a, b), (b, a)):
        entrants = [{"name": n, "spec": specs[n], "sha256": _sha256(specs[n]), "step_budget": 0.5} for n in grid]
        spec = {"kind": "head_to_head", "race": "head_to_head", "track": track, "reverse": False, "seed": seed,
                "trial": 0, "laps": 1, "max_steps": steps, "entrants": entrants}
        for car in run_match(spec, Path("/"), None)["cars"]:
            score[car["name"]][0] -= car["position"]
            score[car["name"]][1] += car["laps"] * 100 + (car.get("progress") or 0.0)
    return a, b, seed, max((a, b), key=lambda n: (score[n], n == min(a, b)))


def _sha256(spec: str) -> str | None:
    return None if spec.startswith("bot:") else hashlib.sha256(Path(spec).read_bytes()).hexdigest()


class Outcomes:
    """Real heat results, cached in a JSON file (a pair on a seed is raced once)."""

    def __init__(self, path: Path, specs: dict, track: str, steps: int, workers: int):
        self.path, self.specs, self.track, self.steps, self.workers = path, specs, track, steps, workers
        self.known = json.loads(path.read_text()) if path.is_file() else {}

    def race(self, heats: list[tuple[str, str, int]]) -> None:
        """Race the heats not in the cache, saving the cache after each."""
        todo = [h for h in heats if self._key(*h) not in self.known]
        if not todo:
            return
        with ProcessPoolExecutor(self.workers) as pool:
            tasks = [(a, b, s, self.specs, self.track, self.steps) for a, b, s in todo]
            for a, b, seed, winner in pool.map(_play, tasks):
                self.known[self._key(a, b, seed)] = winner
                self.path.write_text(json.dumps(self.known, sort_keys=True))

    def winner(self, a: str, b: str, seed: int) -> str:
        return self.known[self._key(a, b, seed)]

    @staticmethod
    def _key(a, b, seed) -> str:
        return f"{min(a, b)}|{max(a, b)}|{seed}"


def _chain(outcomes: Outcomes, names, schedule: str, batch: int, seed: int, salt: int):
    """One chain of a schedule on one seed's outcomes: yields (pairings so far, ranking by ordinal)."""
    from openskill.models import PlackettLuce

    model = PlackettLuce()
    pairs = list(itertools.combinations(names, 2))
    random.Random(salt).shuffle(pairs)  # the round robin's order
    ratings, met = rate(model, names, []), set()
    while len(met) < len(pairs):
        if schedule == "uncertainty":
            chosen = uncertain_heats(model, ratings, batch, met, salt=str(salt))
        else:
            chosen = pairs[len(met):len(met) + batch]
        for a, b in chosen:
            met.add(frozenset((a, b)))
            w = outcomes.winner(a, b, seed)
            new = model.rate([[ratings[w]], [ratings[b if w == a else a]]], ranks=[1, 2])
            ratings[w], ratings[b if w == a else a] = new[0][0], new[1][0]
        yield len(met), sorted(names, key=lambda n: (-ratings[n].ordinal(), n))


def _tau_at(curve: dict, pairings: int) -> float:
    """A chain's tau after its last batch within `pairings`."""
    return curve[max(n for n in curve if n <= pairings)]


def _spread(found: list, never: int) -> dict:
    """Median and range of pairings over chains; a chain that never got there counts as `never` + 1."""
    values = [n if n is not None else never + 1 for n in found]
    return {"median": statistics.median(values), "range": [min(values), max(values)],
            "chains_there": sum(n is not None for n in found)}


def measure(entrants: dict, out: Path, track: str = "reinvent_base", steps: int = 100, batch: int = 16,
            workers: int = 2, chains: int = 8) -> dict:
    """Pairings until a chain's top 8 agrees with the full round robin (tau >= 0.9 for two batches running),
    per schedule and chain; `entrants` maps names to agent files or bot specs. Writes OUT and its heat cache."""
    names = sorted(entrants)
    outcomes = Outcomes(out.with_suffix(".heats.json"), entrants, track, steps, workers)
    outcomes.race([(a, b, s) for a, b in itertools.combinations(names, 2) for s in SEEDS])
    rank = reference_rank(names, outcomes.winner)
    pairs = list(itertools.combinations(names, 2))
    result = {"entrants": len(names), "track": track, "max_steps": steps, "batch": batch,
              "races": 2 * len(SEEDS) * len(pairs),  # both grid orders of every pairing on every seed
              "reference": sorted(names, key=lambda n: (rank[n], n)), "reference_rank": rank}
    for schedule in ("uncertainty", "round_robin"):
        runs = []
        for c in range(chains):
            curve = {count: round(top_tau(ranking, rank), 3) for count, ranking in
                     _chain(outcomes, names, schedule, batch, SEEDS[c % 2], c)}
            counts = list(curve)
            agrees = next((n for n, after in zip(counts, counts[1:])
                           if curve[n] >= TARGET and curve[after] >= TARGET), None)
            holds = next((n for i, n in enumerate(counts) if all(curve[m] >= TARGET for m in counts[i:])), None)
            runs.append({"seed": SEEDS[c % 2], "salt": c, "agrees_at": agrees, "settled_at": holds,
                         "curve": curve})
        result[schedule] = {"chains": runs, **{key: _spread([r[key] for r in runs], len(pairs))
                                               for key in ("agrees_at", "settled_at")},
                            "tau_at": {n: [_tau_at(r["curve"], n) for r in runs] for n in CHECKPOINTS}}
    out.write_text(json.dumps(result, indent=2))
    return result


def league_of_32() -> dict:
    """32 entrants: the shipped agents and bots of four kinds and many speeds."""
    from ..resources import agents_dir

    entrants = {p.stem: str(p) for p in sorted(agents_dir().glob("*.pt"))}
    speeds = [0.6, 0.8, 1.0, 1.2, 1.4, 1.6, 1.8, 2.0]
    bots = ([f"bot:follow@{s}" for s in speeds] + [f"bot:lanes@{s}" for s in speeds]
            + [f"bot:pass@{s}" for s in speeds[1:7]] + [f"bot:racingline@{s}" for s in (0.5, 0.6, 0.7, 0.8, 0.9, 1.0)])
    entrants.update({b: b for b in bots[:32 - len(entrants)]})
    return entrants


if __name__ == "__main__":
    found = measure(league_of_32(), Path(sys.argv[1]))
    print(json.dumps({"races": found["races"], **{s: {k: found[s][k] for k in ("agrees_at", "settled_at", "tau_at")}
                                                  for s in ("uncertainty", "round_robin")}}))
