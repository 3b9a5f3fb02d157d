"""experiments/standard_tasks.py: the environment steps a method's learning episodes used."""

import importlib.util
import os
import types

import numpy as np
from conftest import ROOT


def _script():
    spec = importlib.util.spec_from_file_location(
        "standard_tasks", os.path.join(ROOT, "experiments", "standard_tasks.py"))
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_steps_used_sums_the_episodes_lengths_before_their_ends(tmp_path):
    """Two seeds, three updates of 4 episodes of up to 50 steps: the mean length is the mean
    return over the mean reward per step, and the full length where that reward is 0."""
    mean_return = np.array([[[10.0, 20.0, 5.0], [-6.0, 0.0, 50.0]]])  # (methods, seeds, updates)
    mean_reward = np.array([[[1.0, 2.0, 0.5], [-0.5, 0.0, 1.0]]])
    np.savez(tmp_path / "results.npz", mean_return=mean_return, mean_reward=mean_reward)
    cfg = types.SimpleNamespace(episodes_per_update=4, episode_length=50, episode_end="mask",
                                num_updates=3)
    used = _script().steps_used(str(tmp_path), cfg)
    # seed 0: lengths 10, 10, 10; seed 1: 12, 50 (no reward: the full length), 50
    np.testing.assert_array_equal(used, [4 * 30, 4 * 112])
    # restarted episodes fill their slots: every slot is a step
    cfg.episode_end = "restart"
    np.testing.assert_array_equal(_script().steps_used(str(tmp_path), cfg), [600, 600])
