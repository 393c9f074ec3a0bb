"""The declared track split: training recipes and `multirace evaluate` never share a track."""
from multirace.sim.tracks import list_tracks
from multirace.train.splits import HELD_OUT_TRACKS, TRAINING_SPLIT, expand_tracks, training_tracks


def test_the_split_covers_every_bundled_track_once():
    held, train = set(HELD_OUT_TRACKS), set(training_tracks())
    assert held <= set(list_tracks()) and not held & train and held | train == set(list_tracks())


def test_same_season_siblings_are_held_out_together():
    for a, b in (("2022_april_open", "2022_april_pro"), ("2022_september_open", "2022_september_pro"),
                 ("arctic_open", "arctic_pro")):
        assert a in HELD_OUT_TRACKS and b in HELD_OUT_TRACKS


def test_train_split_word_expands_in_place_without_duplicates():
    tracks = expand_tracks(["Monaco", TRAINING_SPLIT, "Mexico_track"])
    assert tracks[0] == "Monaco" and tracks[-1] == "Mexico_track" and len(tracks) == len(set(tracks))
    assert set(tracks) == set(training_tracks()) | {"Mexico_track"}
