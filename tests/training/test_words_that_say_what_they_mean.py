"""Words that say what a number means: the first line of a training (how many seeds, ``--total-steps`` per seed), the
reader trainer's progress words (the head reward it optimises, the head's success as ``evaluate`` reports it) and a
trajectory picture's title (how its episode was picked among the others). Host strings only: no env."""

from __future__ import annotations

import numpy as np

from baselines.evaluate.pictures import picked_words
from baselines.harness.runner import seeds_line
from baselines.reading.train_readers import progress_words


def test_a_training_says_how_many_seeds_and_that_total_steps_is_per_seed():
    """Was: "PPO on HistoJAX-Easy-v0: 32 updates x 2048 env steps x 4 seeds": the 4 seeds a user did not ask for,
    and 4 x the env steps they gave, went unsaid."""
    line = seeds_line("ppo", {"num_seeds": 4, "env_id": "HistoJAX-Easy-v0"}, 32, 2048)
    assert line == (
        "PPO on HistoJAX-Easy-v0: 4 seeds (--seeds), 65,536 env steps each (--total-steps is per seed; "
        "262,144 in all): 32 updates x 2,048 env steps"
    )
    one = seeds_line("dqn", {"num_seeds": 1, "env_id": "E"}, 10, 100, unit="chunks")
    assert one.startswith("DQN on E: 1 seed (--seeds), 1,000 env steps (--total-steps is per seed; 1,000 in all)")


def test_the_reader_trainers_progress_words_name_the_head_reward_and_the_heads_success():
    line = progress_words("fidelity", 0.0, 0.0)
    assert line.startswith("progress lines: return = the head reward per episode (the head's fidelity gain per read)")
    assert "success = the head's diagnosis right at the episode's end" in line and "histojax evaluate" in line
    both = progress_words("log", 1.0, 0.05)
    assert "1 when the head is right at the end, minus 0.05 per read" in both
    assert "no term" in progress_words("none", 0.0, 0.0)


def test_a_picked_trajectory_says_it_was_picked():
    """Was: the greedy trajectory of a policy that failed 82 % of its episodes showed a success, untitled as such."""
    ep = {"success": np.asarray([False, True, False, True] + [False] * 1020)}
    assert picked_words(ep, 1) == "1 of 2 successes among 1,024 episodes"
    assert picked_words({"success": np.zeros(5, bool)}, 0) == "none of 5 episodes succeeded: the first"
    assert picked_words({"success": np.ones(1, bool)}, 0) == "1 of 1 success among 1 episode"
