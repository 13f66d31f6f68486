"""Expert demonstrations as Minari datasets: written, read back by Minari and bit for bit equal to the ``.npz``
recording of the same episodes, cloned by behaviour cloning (directly and through ``train``), and named when
missing. Tiny: two expert episodes of 25 steps, in a temporary datasets folder."""

import json

import numpy as np
import pytest

pytest.importorskip("minari")
pytest.importorskip("stable_baselines3")

from suture_gym.baselines.expert import record, record_minari  # noqa: E402
from suture_gym.baselines.imitation import behaviour_clone, load_demos, load_minari_demos  # noqa: E402

ENV = "SutureGym/NeedleInsert-v3"
DATASET = "suture_gym/NeedleInsert-v3/expert-v0"
SHORT = {"max_episode_steps": 25}


@pytest.fixture(scope="module")
def root(tmp_path_factory):
    folder = tmp_path_factory.mktemp("minari")
    summary = record_minari(ENV, 2, root=folder, seed=3, env_kwargs=SHORT, progress=False, author="test")
    assert summary == {"episodes": 2, "steps": 50, "success_rate": 0.0, "dataset_id": DATASET, "root": str(folder)}
    return folder


def test_the_dataset_is_a_minari_dataset_of_the_expert_episodes(root, tmp_path, monkeypatch):
    import minari

    monkeypatch.setenv("MINARI_DATASETS_PATH", str(root))
    dataset = minari.load_dataset(DATASET)
    assert (dataset.total_episodes, dataset.total_steps) == (2, 50)
    assert dataset.env_spec.id == ENV and dataset.env_spec.max_episode_steps == 25
    episode = next(dataset.iterate_episodes())
    assert episode.observations.shape == (26, *dataset.observation_space.shape)  # the reset's, then each step's
    assert set(episode.infos) == {"tip_force", "cost", "is_success"} and episode.infos["tip_force"].shape == (26,)

    demos = load_minari_demos(DATASET, root=root)
    record(ENV, 2, tmp_path / "demos.npz", seed=3, env_kwargs=SHORT, progress=False)
    npz = load_demos(tmp_path / "demos.npz")
    assert set(demos) == set(npz) - {"episode_seeds", "env_id"}
    for key, value in demos.items():
        assert value.dtype == npz[key].dtype and np.array_equal(value, npz[key]), key
    assert demos["episode_starts"].tolist() == [0, 25] and demos["truncated"].sum() == 2

    with pytest.raises(ValueError, match="already exists"):
        record_minari(ENV, 1, root=root, env_kwargs=SHORT, progress=False)


def test_behaviour_cloning_fits_the_dataset(root):
    from stable_baselines3 import PPO

    from suture_gym.envs.sb3 import make_sb3_vec_env

    demos = load_minari_demos(DATASET, root=root)
    env = make_sb3_vec_env(ENV, 1, max_episode_steps=25)
    model = PPO("MlpPolicy", env, n_steps=16, batch_size=16, seed=0, device="cpu",
                policy_kwargs={"net_arch": [32, 32]})

    def mse() -> float:
        actions, _ = model.predict(demos["observations"], deterministic=True)
        return float(np.mean((actions - demos["actions"]) ** 2))

    before = mse()
    fit = behaviour_clone(model, demos, epochs=300, batch_size=25, learning_rate=3e-3, seed=0)
    assert fit["steps"] == 50 and fit["episodes"] == 2
    after = mse()
    assert after < 0.1 * before, (after, before)
    env.close()


def test_training_clones_a_dataset_by_id(root, tmp_path, monkeypatch):
    from suture_gym.baselines.training import train

    monkeypatch.setenv("MINARI_DATASETS_PATH", str(root))
    hyperparams = {"policy": "MlpPolicy", "n_timesteps": 16, "n_steps": 16, "batch_size": 16, "n_epochs": 1,
                   "env_kwargs": SHORT, "behaviour_cloning": {"dataset": DATASET, "epochs": 2}}
    result = train("ppo", ENV, out_dir=tmp_path, eval_freq=0, checkpoint_freq=0, progress_bar=False,
                   hyperparams=hyperparams)
    cloning = json.loads((result.run_dir / "summary.json").read_text())["behaviour_cloning"]
    assert cloning["dataset"] == DATASET and cloning["steps"] == 50 and cloning["expert_success_rate"] == 0.0
    assert not (result.run_dir / "demos.npz").exists()  # nothing recorded
    with pytest.raises(ValueError, match=r"recorded on 'SutureGym/NeedleInsert-v3', not on 'SutureGym/SutureThrow"):
        train("ppo", "SutureGym/SutureThrow-v3", out_dir=tmp_path, eval_freq=0, checkpoint_freq=0,
              progress_bar=False, hyperparams=hyperparams)


def test_a_missing_dataset_is_named_with_the_folder_and_what_it_holds(root):
    with pytest.raises(FileNotFoundError, match=rf"'suture_gym/Nope-v1/expert-v0' in '{root}'.*{DATASET}"):
        load_minari_demos("suture_gym/Nope-v1/expert-v0", root=root)


def test_noisy_feedback_demonstrations_record_the_experts_own_actions(tmp_path):
    """With action noise the env executes the expert's choice plus noise, clipped to the box; the recording keeps
    both, the Minari dataset as the info ``expert_action``, and cloning fits the expert's choice."""
    from suture_gym.baselines.datasets import EXPERT_ACTION_KEY

    noisy = {"expert": "feedback", "action_noise": 0.3}
    record(ENV, 2, tmp_path / "noisy.npz", seed=3, env_kwargs=SHORT, progress=False, **noisy)
    npz = load_demos(tmp_path / "noisy.npz")
    chosen, taken = npz["expert_actions"], npz["actions"]
    assert chosen.shape == taken.shape == (50, 6)
    assert np.all(np.abs(taken) <= 1.0) and np.abs(taken - chosen).mean() > 0.1
    rng = np.random.default_rng(3)  # episode 0's noise: env seed 3
    expected = np.clip(chosen[0] + 0.3 * rng.standard_normal(6), -1.0, 1.0).astype(np.float32)
    assert np.array_equal(taken[0], expected)

    record_minari(ENV, 2, "suture_gym/NeedleInsert-v3/noisy-v0", root=tmp_path / "minari", seed=3,
                  env_kwargs=SHORT, progress=False, author="test", **noisy)
    demos = load_minari_demos("suture_gym/NeedleInsert-v3/noisy-v0", root=tmp_path / "minari")
    assert np.array_equal(demos["expert_actions"], chosen) and np.array_equal(demos["actions"], taken)

    clean = tmp_path / "clean.npz"
    record(ENV, 1, clean, seed=3, env_kwargs=SHORT, progress=False, expert="feedback")
    assert "expert_actions" not in load_demos(clean) and EXPERT_ACTION_KEY == "expert_action"


@pytest.mark.parametrize(("change", "message"), [
    ({"expert": "oracle"}, "expert must be one of"),
    ({"action_noise": -0.1}, "action_noise must be"),
])
def test_recording_names_a_bad_expert_or_noise(change, tmp_path, message):
    with pytest.raises(ValueError, match=message):
        record(ENV, 1, tmp_path / "x.npz", env_kwargs=SHORT, progress=False, **change)
