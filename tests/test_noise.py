"""The action noise drawn in blocks is the noise drawn step by step, and leaves the generator where it would be."""
import numpy as np

from multirace.environment.noise import BLOCK_STEPS, NoiseBlocks


def test_blocks_give_the_draws_of_one_call_per_step_across_block_ends():
    one_by_one, blocks = np.random.default_rng(11), NoiseBlocks(np.random.default_rng(11), (3, 2))
    for _ in range(BLOCK_STEPS + 5):
        assert blocks.next() == one_by_one.standard_normal((3, 2)).ravel().tolist()


def test_settle_leaves_the_generator_where_step_by_step_draws_would():
    for steps in (0, 1, BLOCK_STEPS - 1, BLOCK_STEPS, BLOCK_STEPS + 7):
        one_by_one, rng = np.random.default_rng(5), np.random.default_rng(5)
        blocks = NoiseBlocks(rng, (4, 2))
        for _ in range(steps):
            one_by_one.standard_normal((4, 2))
            blocks.next()
        blocks.settle()
        assert rng.uniform(size=6).tolist() == one_by_one.uniform(size=6).tolist()  # the boxes' draws after a reset
        assert blocks.next() == one_by_one.standard_normal((4, 2)).ravel().tolist()  # and the next episode's noise
