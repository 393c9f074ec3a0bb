"""`multirace.load_agent(path)`: any agent file as a policy to call from Python.

    policy = multirace.load_agent("agents/dagger_fast.pt")      # or a shipped agent's name: "dagger_fast"
    env = multirace.parallel_env(num_cars=1, sensor=policy.sensor)
    observations, _ = env.reset(seed=0)
    steering_degrees, speed = policy.command(observations["car_0"])

`command` gives the greedy action (the most likely discrete action, or the
mean of a continuous one) as DeepRacer's (steering degrees, speed m/s).
"""
from __future__ import annotations

from .agentfile import load_agent as load_agent_file
from ..resources import resolve_agent_path


class Policy:
    """A loaded agent file's greedy driver."""

    def __init__(self, agent):
        self.agent = agent
        self.name = agent.name
        self.metadata = agent.metadata
        self.image_shape = tuple(agent.image_shape)  # (height, width, channels) of the camera it reads

    @property
    def sensor(self) -> list[str]:
        """DeepRacer's `sensor` list of the agent (pass it to the env as `sensor=`)."""
        return self.agent.sensors.names

    def command(self, observation) -> tuple[float, float]:
        """(steering degrees, speed m/s) for one env observation: a uint8 image ((H, W) grey), or the env's
        {"camera", "lidar"} dict with a range sensor (what the agent reads of it: `Agent.reads`)."""
        output = self.agent.outputs(self.agent.reads(observation))
        steer, speed = self.agent.action_space.command(self.agent.decide(output[0]))
        return float(steer), float(speed)


def load_policy(path) -> Policy:
    """The agent file at `path` (or a shipped agent's name) as a `Policy`; AgentFileError if it is bad."""
    return Policy(load_agent_file(resolve_agent_path(str(path)), step_budget=None))
