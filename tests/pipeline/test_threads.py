"""train_recipe runs with the recipe's thread count and gives the caller's back (issue 13)."""

import torch
from test_training import write_recipe

from torchfilt.io.synth import simulate_dataset
from torchfilt.pipeline import train_recipe


def test_train_recipe_restores_the_thread_count(tmp_path):
    data = tmp_path / "data"
    simulate_dataset("reaction", data, recordings=4, steps=10, seed=0)
    recipe = write_recipe(tmp_path / "tiny.toml", data, iters=2, every=1)
    recipe.write_text(
        recipe.read_text().replace("checkpoint_every = 1", "checkpoint_every = 1\nthreads = 2")
    )
    before = torch.get_num_threads()
    assert before != 2, "the test needs a caller thread count the recipe changes"
    train_recipe(recipe, tmp_path / "run", progress=False)
    assert torch.get_num_threads() == before
