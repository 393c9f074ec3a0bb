"""multirace: multi-car DeepRacer racing for multi-agent reinforcement learning."""
from .env import RaceEnv, env, parallel_env
from .tracks import Track, TrackError, list_tracks, load_track

__all__ = ["RaceEnv", "Track", "TrackError", "env", "list_tracks", "load_track", "parallel_env"]
__version__ = "0.1.0"
