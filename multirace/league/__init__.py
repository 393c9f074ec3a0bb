"""Leagues: a folder of submitted agents, a deterministic schedule, resumable parallel runs, ratings.

A league is a folder::

    league.toml        the definition (see league/default.toml)
    submissions/       agent files stored by content hash: <sha256>.pt
    results.sqlite     submissions, schedule and results (written transactionally)
    replays/           one rerun recording per match: <match_id>.rrd
    table.md/.csv/...  generated tables (``multirace league table``)

Security: agent files are untrusted. The league process never loads one:
validation at submit time and every race run in worker subprocesses (loading
there is ``torch.load(weights_only=True)``, which refuses pickles that would
import or call code), each match under a wall-clock timeout. A worker that
crashes or hangs is killed and replaced; only its match is retried (a bounded
number of times) and then recorded as failed with the reason.

Resumability: each result is written in one SQLite transaction together with
the schedule row it fulfils (``INSERT OR IGNORE`` keyed by the match id), and
its replay is written under a temporary name and renamed into place before the
result is committed. Killed at any moment and run again, the league runs only
the matches that have no result yet.

Schedules: a round robin (every pair or K-subset meets equally often) or, with
``schedule = "uncertainty"``, pairings planned in batches where the ratings are
close and unsure, each batch from the results before it (``uncertainty.py``;
``convergence.py`` measures how fast it settles the table).
"""
