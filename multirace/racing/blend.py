"""Weight-space blends of two agent files (WiSE-FT: Wortsman et al., "Robust fine-tuning of zero-shot models",
2022): ``share`` x one agent's weights + (1 - share) x the other's, for two fine-tunes of the same start (a
fast time-trial agent and a cautious traffic student, say), so that a blend can keep some of each. The two
files must be the same network on the same sensors and action space; a blend of unrelated networks is
refused, although nothing can tell a blend of two unrelated trainings of the same network from a useful one
(their weights do not line up: race the blend before trusting it)."""
from __future__ import annotations

import copy
from pathlib import Path

from .agentfile import AgentFileError, load_agent, save_agent


def blend_weights(out, start: dict, net, share: float) -> None:
    """`out`'s weights <- `share` x `net`'s + (1 - share) x the `start` state's (same architecture)."""
    state = net.state_dict()
    out.load_state_dict({key: share * value + (1.0 - share) * start[key] if value.is_floating_point() else value
                         for key, value in state.items()})


def blend_agents(first, second, share: float, out, name: str | None = None) -> Path:
    """Write the agent file `out`: `share` x `first`'s weights + (1 - share) x `second`'s, with `first`'s
    metadata (its name: `name`, default `out`'s stem) and a `training` record of what was blended. An
    AgentFileError names the file and the field where the two do not match."""
    if not 0.0 <= share <= 1.0:
        raise ValueError(f"share {share!r}: the share of the first agent's weights is between 0 and 1")
    agents = [load_agent(path, step_budget=None) for path in (first, second)]
    a, b = agents
    for field, read in (("neural_network", lambda agent: agent.metadata.get("neural_network")),
                        ("image", lambda agent: agent.image_shape), ("sensor", lambda agent: agent.sensors.names),
                        ("action_space", lambda agent: agent.action_space.to_metadata())):
        if read(a) != read(b):
            raise AgentFileError(f"{b.path}: model_metadata field {field!r} reads {read(b)!r}, but {a.path}'s "
                                 f"{read(a)!r}: only the same network on the same sensors and action space can be "
                                 f"blended")
    mine, theirs = a.net.state_dict(), b.net.state_dict()
    for key, value in mine.items():
        if key not in theirs or theirs[key].shape != value.shape:
            found = "no such tensor" if key not in theirs else f"shape {tuple(theirs[key].shape)}"
            raise AgentFileError(f"{b.path}: weight {key!r}: {found}, but {a.path} has shape {tuple(value.shape)}")
    net = copy.deepcopy(a.net)
    blend_weights(net, theirs, a.net, share)
    out = Path(out)
    metadata = dict(a.metadata, name=name or out.stem)
    metadata["training"] = {"method": "weight blend (WiSE-FT)", "share_of_first": share,
                            "blended": [{"name": agent.name, "sha256": agent.sha256,
                                         "training": agent.metadata.get("training")} for agent in agents]}
    return save_agent(out, net, metadata, verify=True)
