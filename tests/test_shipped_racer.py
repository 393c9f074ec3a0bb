"""The shipped flagship racer: trained away from the held-out split, and racing held-out tracks at pace."""
import pytest

from multirace.racing.agentfile import load_agent
from multirace.resources import agents_dir
from multirace.train.evaluate import race_agent, reference_lap, trained_tracks
from multirace.train.splits import HELD_OUT_TRACKS

RACER = agents_dir() / "racer.pt"


def test_racer_never_trained_on_a_held_out_track():
    seen = trained_tracks(RACER)
    assert len(seen) >= 30 and not seen & set(HELD_OUT_TRACKS)
    training = load_agent(RACER).metadata["training"]
    assert training["method"] == "dagger" and training["expert"].startswith("bot:racingline")
    assert training["randomize"] == "mild" and training["directions"] == ["forward", "reverse"]


@pytest.mark.parametrize("track,reverse", [("Mexico_track", False), ("Canada_Training", True)])
def test_racer_laps_a_held_out_track_clean_near_the_racing_line(track, reverse):
    row = race_agent(RACER, track, reverse=reverse, laps=2, seed=0, step_budget=1.0)
    assert row["clean"], row
    assert row["best_lap"] <= 1.25 * reference_lap(track, reverse, 2)
