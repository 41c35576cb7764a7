"""How PPO cuts an update's rollout into minibatches: every sample shuffled (``minibatch_by="sample"``, the default)
or whole env sequences (``"env"``, so a minibatch holds only its envs' episodes and slides), and a run recorded
before the choice existed still continues."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from ppo_configs import TINY

from baselines import ppo, ppo_rnn
from baselines.harness.run_folder import _same, difference

NUM_STEPS, NUM_ENVS = 6, 8


def _rollout():
    """A time-major rollout whose entries name their (step, env): ``(num_steps, num_envs)`` and a feature axis."""
    step, env = np.meshgrid(np.arange(NUM_STEPS), np.arange(NUM_ENVS), indexing="ij")
    obs = np.stack([step, env], axis=-1).astype(np.float32)  # (T, E, 2)
    return {"obs": jnp.asarray(obs), "env": jnp.asarray(env), "step": jnp.asarray(step)}


@pytest.mark.parametrize("by_env", [False, True])
def test_the_minibatches_of_an_epoch_hold_every_sample_once(by_env):
    mbs = ppo.split_minibatches(jax.random.PRNGKey(3), _rollout(), 4, by_env)
    assert mbs["obs"].shape == (4, NUM_STEPS * NUM_ENVS // 4, 2)
    pairs = sorted(zip(np.asarray(mbs["step"]).ravel().tolist(), np.asarray(mbs["env"]).ravel().tolist()))
    assert pairs == sorted((t, e) for t in range(NUM_STEPS) for e in range(NUM_ENVS))
    # the leaves stay aligned: each sample's observation is its own (step, env)
    np.testing.assert_array_equal(mbs["obs"][..., 0], mbs["step"].astype(np.float32))
    np.testing.assert_array_equal(mbs["obs"][..., 1], mbs["env"].astype(np.float32))


def test_minibatches_by_env_are_whole_env_sequences():
    """Each minibatch holds all steps of ``num_envs / num_minibatches`` envs, and nothing of any other env."""
    mbs = ppo.split_minibatches(jax.random.PRNGKey(5), _rollout(), 4, by_env=True)
    seen = set()
    for i in range(4):
        envs = set(np.asarray(mbs["env"][i]).tolist())
        assert len(envs) == NUM_ENVS // 4
        for e in envs:
            assert sorted(np.asarray(mbs["step"][i])[np.asarray(mbs["env"][i]) == e].tolist()) == list(range(NUM_STEPS))
        seen |= envs
    assert seen == set(range(NUM_ENVS))


def test_minibatches_by_sample_mix_the_envs():
    """The default shuffles every sample: a minibatch of 12 of these 48 samples draws from more than 2 envs."""
    mbs = ppo.split_minibatches(jax.random.PRNGKey(5), _rollout(), 4, by_env=False)
    assert all(len(set(np.asarray(mbs["env"][i]).tolist())) > NUM_ENVS // 4 for i in range(4))


def test_with_one_minibatch_both_ways_make_the_same_update():
    """One minibatch is the whole rollout either way, in another order: the loss is a mean, so both trainings end
    with the same parameters (to float rounding), and the choice is recorded in the run's config."""
    from baselines.harness.runner import run_seeds

    keys = jax.random.split(jax.random.PRNGKey(0), 1)
    got = {}
    for by in ("sample", "env"):
        trainer = ppo.make_train({**TINY, "num_minibatches": 1, "minibatch_by": by})
        assert trainer.config["minibatch_by"] == by
        got[by] = run_seeds(trainer, keys)["params"]
    for a, b in zip(jax.tree.leaves(got["sample"]), jax.tree.leaves(got["env"])):
        assert np.all(np.isfinite(a))
        np.testing.assert_allclose(a, b, rtol=1e-4, atol=1e-5)


@pytest.mark.parametrize(
    "change, words",
    [
        ({"minibatch_by": "slide"}, "minibatch_by='slide'"),
        ({"minibatch_by": "env", "num_envs": 6, "num_minibatches": 4}, "num_envs=6 must divide by num_minibatches=4"),
    ],
)
def test_a_minibatch_choice_ppo_cannot_make_is_refused_in_one_line(change, words):
    with pytest.raises(ValueError, match=words.replace("(", r"\(")):
        ppo.make_train({**TINY, **change})


def test_recurrent_ppo_always_draws_whole_env_sequences_and_does_not_record_it():
    assert "minibatch_by" not in ppo_rnn.DEFAULTS
    with pytest.raises(ValueError, match="whole env sequences"):
        ppo_rnn.make_train({**TINY, "minibatch_by": "sample"})


def test_a_run_recorded_before_minibatch_by_existed_is_of_the_default_command():
    saved = {**ppo.DEFAULTS}
    del saved["minibatch_by"]
    assert _same(saved, {**ppo.DEFAULTS})
    assert not _same(saved, {**ppo.DEFAULTS, "minibatch_by": "env"})
    assert 'minibatch_by is "sample", not "env"' in difference(saved, {**ppo.DEFAULTS, "minibatch_by": "env"})
