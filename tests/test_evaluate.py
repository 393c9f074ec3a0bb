"""`multirace evaluate`: held-out tracks are tracks the agent never trained on; outputs land where asked."""
import json

import pytest

from multirace.cli import main
from multirace.resources import agents_dir
from multirace.train.evaluate import HELD_OUT_TRACKS, held_out_tracks, trained_tracks

AGENT = agents_dir() / "dagger_small.pt"


def test_quick_split_never_holds_out_a_track_the_agent_trained_on():
    seen = trained_tracks(AGENT)
    assert {"Oval_track", "Bowtie_track", "reInvent2019_track", "reinvent_base"} <= seen
    quick = held_out_tracks(seen, quick=True)
    assert len(quick) == 3 and not set(quick) & seen and set(quick) <= set(HELD_OUT_TRACKS)
    assert not set(held_out_tracks(seen)) & seen


def test_evaluate_labels_trained_tracks_and_writes_its_png_next_to_the_json(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    out = tmp_path / "report" / "r.json"  # a folder that does not exist yet is made
    assert main(["evaluate", str(AGENT), "--quick", "--tracks", "Oval_track,Mexico_track", "--laps", "1",
                 "--json", str(out)]) == 0
    report = json.loads(out.read_text())
    rows = {r["track"]: r for r in report["held_out"]}
    assert rows["Oval_track"]["trained_on"] and not rows["Mexico_track"]["trained_on"]
    assert (tmp_path / "report" / "r.png").stat().st_size > 1000
    assert not (agents_dir() / "dagger_small.eval.png").exists()
    # the held-out figures leave out the track it trained on
    assert report["summary"]["held_out_completion"] == rows["Mexico_track"]["completion"]


def test_held_out_rows_carry_the_racing_line_reference_and_clean_runs_both_ways(tmp_path):
    out = tmp_path / "r.json"
    assert main(["evaluate", str(AGENT), "--quick", "--tracks", "Mexico_track", "--laps", "1", "--directions",
                 "both", "--randomize", "mild", "--json", str(out)]) == 0
    report = json.loads(out.read_text())
    assert report["randomize"] == "mild" and report["directions"] == "both"
    rows = report["held_out"]
    assert sorted(r["reverse"] for r in rows) == [False, True]
    for row in rows:  # a 1 m/s imitation agent against the racing line's ~6 s lap
        assert 5.0 < row["reference_lap"] < 7.0
        assert row["lap_ratio"] == row["best_lap"] / row["reference_lap"] and row["lap_ratio"] > 2.5
        assert row["clean"] == (row["laps"] == 1 and row["off_tracks"] == 0)
    summary = report["summary"]
    assert summary["held_out_runs"] == 2
    assert summary["held_out_clean_share"] == sum(r["clean"] for r in rows) / 2
    assert summary["held_out_clean_within_1_25_share"] == 0.0


def test_heats_report_places_and_collisions_caused_per_lap_of_every_entrant(tmp_path):
    out = tmp_path / "heats.json"
    assert main(["evaluate", str(AGENT), "--parts", "heats", "--heats", "1", "--first-heat", "4", "--heat-tracks",
                 "Mexico_track", "--field", "bot:follow@1.0,dagger_fast", "--json", str(out)]) == 0
    report = json.loads(out.read_text())
    assert report["held_out"] == [] and report["perturbations"] == [] and report["traffic"] == []
    (heat,) = report["heats"]
    assert heat["track"] == "Mexico_track" and heat["seed"] == 4 and heat["laps"] == 3  # --first-heat 4
    assert [c["entrant"] for c in heat["cars"]] == ["dagger_small", "bot:follow@1.0", "dagger_fast"]
    assert sorted(c["position"] for c in heat["cars"]) == [1, 2, 3]
    figures = report["summary"]["heats"]["Mexico_track"]
    assert figures == report["summary"]["heats"]["all"]
    for car in heat["cars"]:
        entrant = figures[car["entrant"]]
        assert entrant["first"] == (car["position"] == 1) and entrant["collisions_caused"] == car["collisions_caused"]
        assert entrant["caused_per_lap"] == car["collisions_caused"] / max(car["laps_driven"], 0.25)
        assert entrant["penalties"] == car["penalties"] and entrant["overtakes"] == car["overtakes"]
        assert car["overtakes_completed"] <= min(car["overtakes"], car["overtakes_attempted"])
    assert sum(c["overtakes"] for c in heat["cars"]) == sum(c["overtaken"] for c in heat["cars"])
    assert figures["dagger_small"]["caused_into_crash"] == sum(i["into_crash"] for i in heat["incidents"])
    assert all(isinstance(i["into_crash"], bool) for i in heat["incidents"])
    assert (tmp_path / "heats.png").exists()


def test_an_incident_is_into_a_crash_only_where_the_car_hit_lost_more_speed_than_brakes_shed():
    from multirace.sim.car import CarSpec
    from multirace.train.heats import stopped_by_crash

    brake, dt = CarSpec().brake, 1 / 15  # 0.4 m/s a step at most
    assert not stopped_by_crash([2.0, 1.6, 1.2, 0.8, 0.4, 0.0], brake, dt)  # full braking to a stop
    assert not stopped_by_crash([0.9, 0.8, 0.9, 0.85], brake, dt)  # a slow car, steady
    # a heat's car ahead (2026-11-29, re:Invent 2018 seed 1) that ran into a third car: 1.96 -> 0.45 in a step
    assert stopped_by_crash([1.611, 1.739, 1.884, 1.855, 1.873, 1.963, 0.45], brake, dt)
    assert not stopped_by_crash([], brake, dt) and not stopped_by_crash([1.5], brake, dt)


@pytest.mark.slow
def test_evaluate_scenarios_report_a_success_rate_per_scenario(tmp_path, capsys):
    from multirace.train.scenarios import SCENARIOS

    out = tmp_path / "scenarios.json"
    assert main(["evaluate", str(AGENT), "--parts", "scenarios", "--scenarios", "1", "--json", str(out)]) == 0
    report = json.loads(out.read_text())
    assert [r["scenario"] for r in report["scenarios"]] == [s.name for s in SCENARIOS]
    summary = report["summary"]["scenarios"]
    for row in report["scenarios"]:
        passed = row["passed_at"] is not None and row["ahead_at_end"]
        assert summary[row["scenario"]] == {"runs": 1, "passed": int(passed), "passed_cleanly": int(row["success"]),
                                            "success_rate": float(row["success"])}
        assert row["success"] == (row["passed_at"] is not None and row["ahead_at_end"] and not row["fouled"]
                                  and not row["void"])
    assert "overtake scenarios" in capsys.readouterr().out


def test_the_default_heat_field_is_the_other_shipped_agents_and_bot_follow(tmp_path):
    from multirace.resources import list_agents
    from multirace.train.heats import default_field, left_out

    copy = tmp_path / "mine.pt"
    copy.write_bytes(AGENT.read_bytes())  # a copy of a shipped file is not raced against itself
    field = default_field(copy)
    others = [n for n in list_agents() if n != "dagger_small"]
    assert field == others[:6] + ["bot:follow@1.0"] and left_out(copy) == others[6:]  # a heat holds 8 cars


def test_evaluate_refuses_bad_parts_heats_entrants_and_heat_tracks_up_front(capsys):
    assert main(["evaluate", str(AGENT), "--parts", "held-out,laps"]) == 2
    assert "--parts: laps is not a part" in capsys.readouterr().err
    assert main(["evaluate", str(AGENT), "--heats", "-1"]) == 2
    assert "--heats: must be at least 0, got -1" in capsys.readouterr().err
    # a bad heat entrant or track is refused before the held-out part spends minutes racing
    assert main(["evaluate", str(AGENT), "--heats", "1", "--field", "bot:follow@1.0,nosuch"]) == 2
    assert "--field: nosuch: no such agent file" in capsys.readouterr().err
    assert main(["evaluate", str(AGENT), "--heats", "1", "--field", "bot:zoom@1"]) == 2
    assert "--field: bot 'bot:zoom@1'" in capsys.readouterr().err
    assert main(["evaluate", str(AGENT), "--heats", "1", "--heat-tracks", "Mexico_track,Nowhere"]) == 2
    assert "--heat-tracks: track 'Nowhere'" in capsys.readouterr().err
    assert main(["evaluate", str(AGENT), "--scenarios", "1", "--scenario-track", "Nowhere"]) == 2
    assert "--scenario-track: track 'Nowhere'" in capsys.readouterr().err


def test_evaluate_refuses_a_damaged_agent_file_before_any_race(tmp_path, capsys):
    """A file that cannot race is an error naming it, not a report of 0-lap forfeits."""
    broken = tmp_path / "broken.pt"
    data = AGENT.read_bytes()
    broken.write_bytes(data[: len(data) // 2])
    report = tmp_path / "report.json"
    assert main(["evaluate", str(broken), "--parts", "held-out", "--json", str(report)]) == 2
    err = capsys.readouterr().err
    assert err.startswith("multirace evaluate: error: ") and "broken.pt" in err
    assert not report.exists()


def test_the_report_figure_draws_zero_counts_from_zero_and_plots_traffic():
    import matplotlib.pyplot as plt

    from multirace.train.evaluate import SUMMARY_LABELS, race_agent, report_figure, summarise

    agent = str(agents_dir() / "dagger_small.pt")
    short = race_agent(agent, "Oval_track", laps=1, max_steps=20)  # 20 steps: no lap, no off-track, no contact
    traffic = race_agent(agent, "Oval_track", laps=1, bots=("follow@0.8",), race="head_to_head", max_steps=20)
    assert short["off_tracks_per_lap"] in (0, 0.0, None) and traffic["collisions_per_lap"] in (0, 0.0, None)
    report = {"agent": agent, "reference_track": "Oval_track", "laps": 1, "trained_on": [],
              "held_out": [short], "perturbations": [dict(short, perturbation="none")], "traffic": [traffic]}
    report["summary"] = summarise(report)
    assert set(report["summary"]) <= set(SUMMARY_LABELS)  # the printed summary names every figure in words
    fig = report_figure([report])
    held, perturbed, off_tracks, traffic_panel = fig.axes
    for ax in fig.axes:  # every count is 0: each panel starts at 0 and shows a positive range
        low, high = ax.get_ylim()
        assert low == 0 and high > 0, ax.get_title()
    assert "traffic" in traffic_panel.get_title()
    assert [t.get_text() for t in traffic_panel.get_xticklabels()] == ["lap completion", "collisions/lap", "caused/lap"]
    plt.close(fig)


def test_the_default_heat_field_of_an_agent_that_is_not_shipped_fits_in_a_race(tmp_path):
    """The shipped agents, the bot and an agent of one's own are more cars than the eight a heat holds."""
    from multirace.environment.race_env import MAX_CARS
    from multirace.resources import list_agents
    from multirace.train.heats import check_heats, default_field, left_out

    mine = tmp_path / "mine.pt"
    mine.write_bytes(AGENT.read_bytes() + b"\0")  # not the content of any shipped file
    field = default_field(mine)
    assert len(field) + 1 <= MAX_CARS and field[-1] == "bot:follow@1.0"
    assert sorted(field[:-1] + left_out(mine)) == list_agents()
    check_heats(["reinvent_base"], field)  # what evaluate races by default, it accepts
    with pytest.raises(ValueError, match="--field: 8 entrants and the agent make 9 cars"):
        check_heats(["reinvent_base"], list_agents()[:7] + ["bot:follow@1.0"])
