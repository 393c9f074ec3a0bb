"""Time trials of an RL teacher (a ``FILE.teacher.pt`` of `train --privileged`) on a track split, from its
privileged state: ``python -m multirace.tools.teacher_eval split60.teacher.pt --split held-out``.

A teacher is not an agent file (it reads the state, not a camera), so `multirace evaluate` does not race it;
this shows whether a student's off-tracks are its own or its teacher's. Each track is raced in both
directions, nominal car, under the race rules with DeepRacer's action noise (`teacher.evaluate_teacher`).
"""
from __future__ import annotations

import argparse
import json


def evaluate_split(path, tracks: list[str], laps: int = 2, seed: int = 0, log=print) -> list[dict]:
    """One time trial of the teacher file per track and direction; rows with the racing line's lap for scale."""
    from ..train.evaluate import reference_lap
    from ..train.teacher import evaluate_teacher
    from ..train.teacher_net import load_teacher

    net = load_teacher(path)
    rows = []
    for track in tracks:
        for reverse in (False, True):
            row = evaluate_teacher(net, net.space, track, laps=laps, seed=seed, reverse=reverse)
            reference = reference_lap(track, reverse=reverse)
            row.update(track=track, reverse=reverse, racing_line=reference,
                       ratio=round(row["best_lap"] / reference, 3) if row["best_lap"] else None,
                       clean=row["laps"] == laps and row["resets"] == 0)
            rows.append(row)
            if log:
                ratio = f"{row['ratio']:.3f}x" if row["ratio"] else "-"
                log(f"{track}{' reverse' if reverse else ''}: {row['laps']}/{laps} laps, {row['resets']} "
                    f"off-tracks, best lap {ratio} the racing line")
    return rows


def main(argv=None) -> int:
    from ..atomic import write_text
    from ..train.splits import HELD_OUT_TRACKS, training_tracks

    parser = argparse.ArgumentParser(prog="python -m multirace.tools.teacher_eval", description=__doc__.split("\n")[0])
    parser.add_argument("teacher", help="a FILE.teacher.pt written by `multirace train --privileged`")
    parser.add_argument("--split", choices=("held-out", "train"), default="held-out")
    parser.add_argument("--laps", type=int, default=2)
    parser.add_argument("--json", help="write the rows to this JSON file")
    args = parser.parse_args(argv)
    tracks = list(HELD_OUT_TRACKS) if args.split == "held-out" else training_tracks()
    try:
        rows = evaluate_split(args.teacher, tracks, laps=args.laps)
    except ValueError as exc:
        parser.error(str(exc))
    clean = sum(r["clean"] for r in rows)
    ratios = [r["ratio"] for r in rows if r["ratio"]]
    print(f"{args.split}: {clean}/{len(rows)} runs clean, best laps {min(ratios):.2f}-{max(ratios):.2f}x the "
          "racing line" if ratios else f"{args.split}: no lap completed")
    if args.json:
        write_text(args.json, json.dumps(rows, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
