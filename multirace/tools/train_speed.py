"""The PPO loop's speed under several settings, measured in turns in one run (a busy machine's drift hits
every setting alike): ``python -m multirace.tools.train_speed --seconds 40 --rounds 2``.

Each setting is a dict of `TrainConfig` overrides; `SETTINGS` holds the steps of issue 26's faster learner,
each on top of the previous one (`old`: the settings before them), and last the throughput preset with the
learner inferring for every car (no actors) as a control. Figures are in multirace/train/README.md
("Throughput").
"""
from __future__ import annotations

import argparse
import json

SETTINGS = {
    "old": {"pool_inputs": False, "actors": False},
    "+ pooled inputs": {"actors": False},
    "+ actors (the default)": {},
    "+ overlapped update, 8 cars per worker (--config throughput)": {"overlap_update": True, "cars_per_env": 8,
                                                                     "rollout_steps": 128},
    "--config throughput, the learner inferring": {"overlap_update": True, "cars_per_env": 8, "rollout_steps": 128,
                                                   "actors": False},
}


def compare(settings: dict, seconds: float, rounds: int, log=print) -> dict:
    """{name: [figures of each round]} of `training_throughput` for each setting, in turns."""
    from ..train.throughput import training_throughput

    results: dict = {name: [] for name in settings}
    for r in range(rounds):
        for name, overrides in settings.items():
            figures = training_throughput(seconds=seconds, **overrides)
            results[name].append(figures)
            log(f"round {r + 1} {name}: {figures['agent_steps_per_s']:.0f} agent-steps/s, "
                f"{figures['cpu_us_per_agent_step']} CPU us per agent-step, sampling "
                f"{figures['sampling_share']:.2f}, update {figures['update_share']:.2f}")
    return results


def table(results: dict) -> str:
    """A Markdown table: setting, agent-steps/s (mean of the rounds, and each), sampling and update shares."""
    lines = ["| settings | agent-steps/s (mean; rounds) | CPU us per agent-step (mean) | sampling share | "
             "update share |", "|---|---|---|---|---|"]
    for name, rows in results.items():
        rates = [row["agent_steps_per_s"] for row in rows]
        mean = sum(rates) / len(rates)
        share = {key: sum(row[key] for row in rows) / len(rows) for key in ("sampling_share", "update_share")}
        cpu = [row["cpu_us_per_agent_step"] for row in rows if row["cpu_us_per_agent_step"] is not None]
        lines.append(f"| {name} | {mean:,.0f} ({', '.join(f'{v:,.0f}' for v in rates)}) | "
                     f"{sum(cpu) / len(cpu) if cpu else float('nan'):.0f} | "
                     f"{share['sampling_share']:.2f} | {share['update_share']:.2f} |")
    return "\n".join(lines)


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--seconds", type=float, default=40.0, help="training seconds per measurement")
    parser.add_argument("--rounds", type=int, default=2, help="turns through the settings")
    parser.add_argument("--only", nargs="*", help="names of SETTINGS to measure (default: all)")
    parser.add_argument("--extra", type=json.loads, default={}, help='more settings, e.g. {"name": {"epochs": 2}}')
    args = parser.parse_args(argv)
    settings = {k: v for k, v in SETTINGS.items() if not args.only or k in args.only}
    settings.update(args.extra)
    print(table(compare(settings, args.seconds, args.rounds)))


if __name__ == "__main__":
    import torch

    torch.set_num_threads(1)
    main()
