"""Names and texts from files (agent files, replays) are shown as what they read: no terminal escapes, no
right-to-left overrides, zero-width or other format characters reach the terminal or a table."""
import subprocess
import sys

import pytest

from multirace.environment.actions import load_action_space
from multirace.racing.agentfile import make_metadata, save_agent
from multirace.racing.nets import TINY, build_net
from multirace.text import display_name

SPACE = load_action_space(None)
RLO, ZWSP, ZWJ, LRI, BOM, LINE_SEP = "\u202e", "\u200b", "\u200d", "\u2066", "\ufeff", "\u2028"
HIDDEN = (RLO, ZWSP, ZWJ, LRI, BOM, LINE_SEP, "\x1b", "\x07", "\x9b")
# reads "racer" + "exe.gnp" shown right to left, with a zero-width space, a title change, a screen clear and a
# hyperlink
HOSTILE = f"racer{ZWSP}{RLO}gnp.exe{LRI}\x1b]0;pwned\x07\x1b[2J\x1b]8;;http://x\x07link\x1b]8;;\x07{BOM}"


@pytest.mark.parametrize("char", [RLO, ZWSP, ZWJ, LRI, BOM, LINE_SEP, "\u2029", "\u061c", "\u00ad", "\ud800"])
def test_format_and_invisible_characters_are_removed_from_names(char):
    assert display_name(f"a{char}b") == "ab"


def test_a_hostile_name_reads_as_its_visible_letters():
    shown = display_name(HOSTILE)
    assert shown == "racergnp.exelink" and not any(c in shown for c in HIDDEN)
    assert display_name("Zoë 🏎 Ünal") == "Zoë 🏎 Ünal"  # letters and emoji stay


@pytest.fixture(scope="module")
def hostile_replay(tmp_path_factory):
    """A replay of a race of an agent whose name is HOSTILE: the .rrd holds it as written."""
    folder = tmp_path_factory.mktemp("names")
    agent = save_agent(folder / "evil.pt", build_net(TINY, (120, 160, 1), SPACE), make_metadata(SPACE, TINY, HOSTILE))
    replay = folder / "race.rrd"
    done = subprocess.run([sys.executable, "-m", "multirace.cli", "race", str(agent), "bot:follow@1.0", "--laps",
                           "1", "--max-steps", "60", "--replay", str(replay)], capture_output=True, text=True,
                          timeout=300)
    assert done.returncode == 0, done.stderr
    return done.stdout, replay


def test_the_results_table_shows_a_hostile_name_without_hidden_characters(hostile_replay):
    out, _ = hostile_replay
    assert "racergnp.exelink" in out and not any(c in out for c in HIDDEN)


def test_replay_summary_prints_names_and_events_from_a_hostile_file_as_text(hostile_replay):
    from multirace.recording.replay_reader import replay_summary

    _, replay = hostile_replay
    assert any(RLO in car["name"] for car in replay_summary(replay, poses=False)["cars"])  # the file holds it raw
    done = subprocess.run([sys.executable, "-m", "multirace.cli", "replay", str(replay), "--summary"],
                          capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr
    assert "racergnp.exelink" in done.stdout and not any(c in done.stdout for c in HIDDEN)
