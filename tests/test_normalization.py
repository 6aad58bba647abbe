"""VecNormalize's compiled running statistics (``CompiledRunningMeanStd``, ``fast_normalization``
in envs/wrappers.py) against SB3's own ``RunningMeanStd``: the same mean, var and count bit for
bit (types included), on random batch sequences and through a short PPO training; copy, combine,
pickling and VecNormalize.save/load keep the class and the numbers."""

import pickle

import numpy as np
import pytest
from learning_setup import FAST, load_script, rollout
from stable_baselines3.common.running_mean_std import RunningMeanStd
from stable_baselines3.common.vec_env import VecNormalize

from astrocargo.envs.wrappers import (
    CompiledRunningMeanStd,
    compiled_statistics,
    fast_normalization,
    make_vec_env,
)


def assert_same_statistics(compiled, sb3):
    """Bit-equal mean, var and count, of the same types (np.float64 scalars for shape ())."""
    assert isinstance(compiled, CompiledRunningMeanStd)
    for name in ("mean", "var", "count"):
        a, b = getattr(compiled, name), getattr(sb3, name)
        assert type(a) is type(b), name
        assert np.shape(a) == np.shape(b), name
        assert np.asarray(a).tobytes() == np.asarray(b).tobytes(), name


def random_batches(rng, dtype, shape, count, sizes):
    """``count`` batches (rows of ``shape``) of random sizes from ``sizes``: a common offset and
    per-entry scales spanning 12 orders of magnitude, each batch at its own scale."""
    offset = rng.standard_normal(shape) * 10.0 ** rng.uniform(-3, 5)
    scale = 10.0 ** rng.uniform(-6, 6, size=shape)
    for _ in range(count):
        n = int(rng.choice(sizes))
        noise = rng.standard_normal((n, *shape)) * 10.0 ** rng.uniform(-3, 3)
        yield (offset + scale * noise).astype(dtype)


# The layouts numpy sums differently: rows of several entries (row after row), one entry or
# a scalar per row (numpy's pairwise sum: a plain loop below 8 rows, 8 accumulators up to 128,
# halves above), and rows of more than one axis.
SHAPES = [(), (1,), (3,), (17,), (47,), (2, 5), (4, 1)]


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
@pytest.mark.parametrize("shape", SHAPES)
def test_updates_are_sb3s_bit_for_bit(dtype, shape):
    rng = np.random.default_rng([SHAPES.index(shape), np.dtype(dtype).itemsize])
    compiled, sb3 = compiled_statistics(RunningMeanStd(shape=shape)), RunningMeanStd(shape=shape)
    sizes = list(range(1, 33)) + [100, 128, 129, 300]
    for batch in random_batches(rng, dtype, shape, 60, sizes):
        compiled.update(batch)
        sb3.update(batch)
        assert_same_statistics(compiled, sb3)


def test_special_values_and_other_layouts_follow_sb3():
    """Signed zeros, infinities and NaN as numpy gives them; batches the kernel does not take
    (integers, Fortran order) go through SB3's update."""
    rng = np.random.default_rng(3)
    batches = [
        np.full((9, 2), -0.0), np.full((3,), -0.0, np.float32), np.array([[np.inf, 1.0]] * 2),
        np.array([np.nan, 2.0], np.float32), np.array([1e30, -1e30, 3.0], np.float32),
    ]  # fmt: skip
    for batch in batches:
        compiled = compiled_statistics(RunningMeanStd(shape=batch.shape[1:]))
        sb3 = RunningMeanStd(shape=batch.shape[1:])
        with np.errstate(all="ignore"):
            compiled.update(batch)
            sb3.update(batch)
        assert_same_statistics(compiled, sb3)
    for batch in (rng.integers(-5, 5, (6, 3)), np.asfortranarray(rng.standard_normal((6, 3)))):
        compiled, sb3 = compiled_statistics(RunningMeanStd(shape=(3,))), RunningMeanStd(shape=(3,))
        compiled.update(batch)
        sb3.update(batch)
        assert_same_statistics(compiled, sb3)


@pytest.mark.parametrize("shape", [(5,), ()])
def test_copy_combine_and_pickling_keep_class_and_numbers(shape):
    rng = np.random.default_rng(4)
    compiled, sb3 = compiled_statistics(RunningMeanStd(shape=shape)), RunningMeanStd(shape=shape)
    for batch in random_batches(rng, np.float32, shape, 10, [2, 4]):
        compiled.update(batch)
        sb3.update(batch)
    copied = compiled.copy()
    assert_same_statistics(copied, sb3)
    assert_same_statistics(compiled_statistics(sb3), sb3)
    assert_same_statistics(pickle.loads(pickle.dumps(compiled)), sb3)
    other = RunningMeanStd(shape=shape)
    other.update(rng.standard_normal((3, *shape)))
    compiled.combine(other)
    sb3.combine(other)
    assert_same_statistics(compiled, sb3)
    copied.update(batch)  # the copy is apart from the original
    assert_same_statistics(compiled, sb3)


def test_fast_normalization_steps_saves_and_loads_as_sb3(tmp_path):
    def normalized():
        return VecNormalize(make_vec_env(2, seed=7, **FAST), gamma=0.9)

    sb3, compiled = normalized(), fast_normalization(normalized())
    for a, b in zip(rollout(sb3, 45, 1), rollout(compiled, 45, 1), strict=True):
        assert a.dtype == b.dtype and a.tobytes() == b.tobytes()
    assert_same_statistics(compiled.obs_rms, sb3.obs_rms)
    assert_same_statistics(compiled.ret_rms, sb3.ret_rms)
    compiled.save(str(tmp_path / "vecnormalize.pkl"))
    loaded = VecNormalize.load(str(tmp_path / "vecnormalize.pkl"), make_vec_env(2, seed=7, **FAST))
    assert_same_statistics(loaded.obs_rms, sb3.obs_rms)
    assert_same_statistics(loaded.ret_rms, sb3.ret_rms)
    for venv in (sb3, compiled, loaded):
        venv.close()
    with pytest.raises(ValueError, match="no VecNormalize"):
        fast_normalization(make_vec_env(1, **FAST))


def test_short_ppo_training_is_sb3s():
    """train.build_model's PPO (compiled statistics) and the same model on SB3's statistics:
    the same statistics and parameters after two rollouts and updates."""
    train = load_script("train")
    args = train.build_parser().parse_args(
        ["--copies", "2", "--max-cycles", "20", "--noise", "ideal", "--no-estimates"]
        + ["--no-progress-bar", "--hyperparams", "n_steps=32", "batch_size=64", "n_epochs=2"]
    )
    models = []
    for sb3_statistics in (False, True):
        model, _ = train.build_model(args, seed=11)
        venv = model.get_env()
        assert isinstance(venv.obs_rms, CompiledRunningMeanStd)
        if sb3_statistics:
            venv.obs_rms = RunningMeanStd.copy(venv.obs_rms)
            venv.ret_rms = RunningMeanStd.copy(venv.ret_rms)
        model.learn(total_timesteps=256)
        models.append(model)
    compiled, sb3 = (m.get_env() for m in models)
    assert type(sb3.obs_rms) is RunningMeanStd
    assert_same_statistics(compiled.obs_rms, sb3.obs_rms)
    assert_same_statistics(compiled.ret_rms, sb3.ret_rms)
    for (name, a), (_, b) in zip(
        models[0].policy.state_dict().items(), models[1].policy.state_dict().items(), strict=True
    ):
        assert a.numpy().tobytes() == b.numpy().tobytes(), name
    for m in models:
        m.get_env().close()
