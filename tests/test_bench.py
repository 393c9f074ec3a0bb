"""`multirace bench --profile`: the per-stage split of an env step, and the env left as it was."""
import pytest

from multirace.tools.bench import _random_driving, run_profile
from multirace.tools.profile import STAGES, format_profile, profile_step


def test_the_profile_splits_the_step_into_its_stages_and_leaves_the_env_untouched():
    env, step = _random_driving(2)
    try:
        step()
        split = profile_step(step, env, 20)
        assert set(split) == set(STAGES) | {"total"}
        for stage in ("dynamics", "contacts", "rules", "params", "reward", "render"):
            assert split[stage] > 0, stage
        assert sum(split[stage] for stage in STAGES) == pytest.approx(split["total"], abs=0.5)
        # the wrappers are gone: the class's own methods again
        assert "_observe" not in vars(env) and "step" not in vars(env.world) and "_pushes" not in vars(env.world)
        assert "rewards" not in vars(env.reward_function)
    finally:
        env.close()


def test_run_profile_reports_every_stage_and_the_renderer_alone():
    profile = run_profile(num_cars=2, steps=30, progress=lambda line: None)
    labels = [label for label, _ in format_profile(profile)]
    assert labels[:len(STAGES)] == list(STAGES)
    assert profile["renderer_frames_per_s"] > 0 and 0 <= profile["pybullet_step_share"] <= 1

