"""`multirace.load_agent(path)`: any agent file, imported DeepRacer networks included, as a policy.

    policy = multirace.load_agent("agents/dagger_fast.pt")      # or a shipped agent's name: "dagger_fast"
    env = multirace.parallel_env(num_cars=1, sensor=policy.sensor)
    observations, _ = env.reset(seed=0)
    steering_degrees, speed = policy.command(observations["car_0"])

Agent files of multirace's networks load through the agent-file loader
(`racing.policy`); an imported DeepRacer network that no multirace network
matches (metadata field ``deepracer_graph``, see `drnet`) is rebuilt as a `GraphNet`.
"""
from __future__ import annotations

from ..racing.agentfile import parse_metadata, read_payload
from ..racing.policy import Policy, load_policy as load_agent_policy
from ..racing.runner import resolve_agent_path
from .drnet import load_graph_agent


def load_policy(path) -> Policy:
    """The agent file at `path` (or a shipped agent's name) as a policy whose `command(observation)` gives
    the greedy (steering degrees, speed m/s); AgentFileError if the file is bad."""
    resolved = resolve_agent_path(str(path))
    if "deepracer_graph" in parse_metadata(read_payload(resolved), str(resolved)):
        return Policy(load_graph_agent(resolved))
    return load_agent_policy(resolved)
