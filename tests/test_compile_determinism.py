"""The first race after an install (its kernels compiled in the process) is the same race as every later one
(its kernels loaded from numba's cache): a kernel whose rounding depends on how it was compiled would make
the same seeds give another race on a fresh machine."""
import os
import subprocess
import sys

import pytest

RACE = """
import hashlib, json
import numpy as np
from multirace.environment.race_env import RaceEnv
digest = hashlib.sha256()
env = RaceEnv(num_cars=4, obstacles=3, max_steps=300)
rng = np.random.default_rng(7)
env.reset(seed=7)
while env.agents:
    observations, rewards, _, _, infos = env.step({a: int(rng.integers(env.actions.space.n)) for a in env.agents})
    for agent in sorted(observations):
        digest.update(np.ascontiguousarray(observations[agent]).tobytes())
    digest.update(env.world.poses.tobytes())
    digest.update(json.dumps([rewards, infos], sort_keys=True, default=str).encode())
print(digest.hexdigest())
"""


@pytest.mark.slow
def test_a_race_run_while_its_kernels_compile_equals_the_race_run_from_the_cache(tmp_path):
    env = dict(os.environ, NUMBA_CACHE_DIR=str(tmp_path / "numba-cache"))
    runs = [subprocess.run([sys.executable, "-c", RACE], capture_output=True, text=True, timeout=600, env=env)
            for _ in range(2)]
    for run in runs:
        assert run.returncode == 0, run.stderr
    assert "compiling the physics and renderer kernels" in runs[0].stderr  # the first run compiled them
    assert "compiling" not in runs[1].stderr  # the second loaded every one from the cache
    assert runs[0].stdout == runs[1].stdout
