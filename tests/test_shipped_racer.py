"""The shipped flagship racer: trained away from the held-out split, and racing held-out tracks at pace."""
import pytest

from multirace.racing.agentfile import load_agent
from multirace.resources import agents_dir
from multirace.train.evaluate import race_agent, reference_lap, trained_tracks, training_stages
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


LIDAR_RACER = agents_dir() / "racer_lidar.pt"


def test_lidar_racer_reads_the_lidar_never_trained_on_a_held_out_track_and_can_crawl():
    assert not trained_tracks(LIDAR_RACER) & set(HELD_OUT_TRACKS)
    metadata = load_agent(LIDAR_RACER).metadata
    assert metadata["sensor"] == ["FRONT_FACING_CAMERA", "LIDAR"]
    assert metadata["action_space"]["speed"]["low"] <= 0.1  # it can queue behind a slow car at the expert's crawl
    assert metadata["training"]["traffic"] and metadata["training"]["init"]["name"] in ("racer", "racer_lidar")


def test_lidar_racer_laps_a_held_out_track_clean_and_wins_a_heat_there():
    from multirace.sim.car import CarSpec
    from multirace.train.heats import INCIDENT_STEPS, run_heats, summarise_heats

    row = race_agent(LIDAR_RACER, "Mexico_track", reverse=True, laps=2, seed=1, randomize="mild", step_budget=1.0)
    assert row["clean"], row
    assert row["best_lap"] <= 1.25 * reference_lap("Mexico_track", True, 2)
    field = ["dagger_fast", "dagger_small", "racer", "bot:follow@1.0"]  # the field its figures were measured in
    # two heats: a close one (seed 1) is won on one CPU and lost by a length on another (the last bits of the
    # tyre maths, the nets' and numpy's kernels differ between AVX2 and AVX-512 builds, and a race in traffic
    # grows them), so the claim is the pair's: second or better in each, first in at least one
    heats = run_heats(LIDAR_RACER, ["2022_april_open"], [1, 2], field=field)
    racers = [heat["cars"][0] for heat in heats]
    assert all(racer["position"] <= 2 and racer["laps"] == 3 for racer in racers), racers
    assert min(racer["position"] for racer in racers) == 1, racers
    # under the race rules it is at fault about 0.4 times a lap on this track (10 heats: README "Race rules"),
    # mostly rear-ending cars it laps
    assert all(racer["collisions_caused"] <= 3 for racer in racers), racers
    kinds = {"rear_end", "side_swipe", "cut_across", "push_off", "obstacle"}  # what the stewards judge
    for heat in heats:
        for car in heat["cars"]:  # every at-fault incident counted once, under its kind
            assert sum(car["caused_kinds"].values()) == car["collisions_caused"] and set(car["caused_kinds"]) <= kinds
        racer = heat["cars"][0]
        summary = summarise_heats([heat])["all"][racer["entrant"]]
        assert summary["caused_kinds"] == racer["caused_kinds"]
        # each of its incidents (heats have no boxes) with the steps that led to it, the last one touching
        incidents = heat["incidents"]
        assert len(incidents) == racer["collisions_caused"]
        assert {kind: sum(i["kind"] == kind for i in incidents) for kind in racer["caused_kinds"]} == \
            racer["caused_kinds"]
        for incident in incidents:
            assert incident["with"] in field and 1 <= len(incident["steps"]) <= INCIDENT_STEPS
            assert abs(incident["steps"][-1]["gap"]) < 2 * CarSpec().length
    assert sum(len(heat["incidents"]) for heat in heats) > 0  # (so the records above were read)


H2H_RACERS = {"racer_h2h": ["FRONT_FACING_CAMERA_TWO_FRAMES"], "racer_h2h_lidar": ["FRONT_FACING_CAMERA", "LIDAR"]}


@pytest.mark.parametrize("name", H2H_RACERS)
def test_h2h_racers_read_their_sensors_and_learnt_from_rl_teachers_away_from_the_held_out_split(name):
    path = agents_dir() / f"{name}.pt"
    assert not trained_tracks(path) & set(HELD_OUT_TRACKS)
    metadata = load_agent(path).metadata
    assert metadata["name"] == name and metadata["sensor"] == H2H_RACERS[name]
    # its own stage, then every file it started from or is a weight blend of
    stages = [stage for stage in training_stages(metadata["training"]) if "blended" not in stage]
    # every student stage was labelled by a privileged RL teacher; only the first file (racer) imitated a bot
    students = [stage for stage in stages if isinstance(stage.get("init"), dict)]
    firsts = [stage for stage in stages if not isinstance(stage.get("init"), dict)]
    assert len(students) >= 2 and all(stage["expert"].startswith("teacher:") for stage in students)
    assert firsts and all(stage["expert"].startswith("bot:racingline") for stage in firsts)


@pytest.mark.parametrize("name", H2H_RACERS)
def test_h2h_racers_win_a_held_out_heat_against_the_shipped_field_without_causing_a_collision(name):
    from multirace.train.heats import default_field, run_heats

    path = agents_dir() / f"{name}.pt"
    field = default_field(path)
    assert len(field) == 7 and name not in field  # six other shipped agents and bot:follow@1.0
    (heat,) = run_heats(path, ["2022_april_open"], [2])
    racer = heat["cars"][0]
    # agents/README.md, the head-to-head racers: first there in 78 and 74 of 80 heats, 6 and 7 incidents in 240
    # laps; in seed 2 both win cleanly
    assert racer["entrant"] == name and racer["position"] == 1 and racer["laps"] == 3
    assert racer["collisions_caused"] == 0 and heat["incidents"] == []
