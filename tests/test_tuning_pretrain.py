"""Cloning in a tuning study (sb3_graph.tuning.pretrain): once per study, cached, reused by every trial."""

import optuna
import pytest
import torch as th
import yaml
from optuna.trial import TrialState

import sb3_graph.toy_envs as toy_envs
from sb3_graph.cli import main
from sb3_graph.tuning.objectives import make_objective
from sb3_graph.tuning.pretrain import default_cache_folder, write_atomically
from sb3_graph.tuning.runner import TrialSettings, run_trial
from sb3_graph.tuning.toy import evaluate_max_neighbour

th.set_num_threads(1)
optuna.logging.set_verbosity(optuna.logging.WARNING)
TOY = "GraphMaxNeighbour-v0"
TINY = {
    "n_timesteps": 60,
    "policy": "GraphPolicy",
    "learning_starts": 20,
    "batch_size": 16,
    "buffer_size": 500,
    "train_freq": 4,
    "policy_kwargs": "dict(encoder_dim=8, conv_dims=[8])",
    "pretrain_from": "exact",
    "pretrain_transitions": 40,
    "pretrain_steps": 5,
    "pretrain_critic_steps": 2,
}


@pytest.fixture
def counted(monkeypatch):
    """Count the toy expert's calls (one per VecEnv step of collecting)."""
    calls = []

    def make_expert(spec, env):
        def expert(obs):
            calls.append(len(obs["x"]))
            return toy_envs.max_neighbour_expert(obs)

        toy_envs_make(spec, env)  # the spec check of the real factory
        return expert

    toy_envs_make = toy_envs.make_expert
    monkeypatch.setattr(toy_envs, "make_expert", make_expert)
    return calls


def settings(folder):
    return TrialSettings(
        env_id=TOY,
        entry=dict(TINY),
        timesteps=60,
        objective=make_objective("flow", max_collision_rate=1.0),
        evaluator=evaluate_max_neighbour,
        evaluations=1,
        eval_episodes=1,
        pretrain_cache=folder,
    )


def test_trials_with_the_same_entry_clone_once_and_start_from_the_same_model(counted, tmp_path):
    models = []
    study = optuna.create_study(direction="maximize")

    def objective(trial):
        value = run_trial(trial, settings(tmp_path / "cache"))
        return value

    import sb3_graph.tuning.pretrain as pretrain  # the runner imports it at each trial

    original = pretrain.pretrain_trial

    def spy(model, *args, **kwargs):
        summary = original(model, *args, **kwargs)
        models.append({k: v.clone() for k, v in model.policy.state_dict().items()})
        return summary

    pretrain.pretrain_trial = spy
    try:
        study.optimize(objective, n_trials=2)
    finally:
        pretrain.pretrain_trial = original
    first, second = study.trials
    assert first.state == second.state == TrialState.COMPLETE
    assert first.user_attrs["pretrain"]["cache"] == "none" and second.user_attrs["pretrain"]["cache"] == "clone"
    assert len(counted) == 40  # 40 steps of one environment, collected by the first trial only
    assert sorted(p.name.split("-")[0] for p in (tmp_path / "cache").iterdir()) == ["clone", "demonstrations"]
    for name, tensor in models[0].items():  # seeds 0 and 1, one cloned model
        assert th.equal(tensor, models[1][name]), name


def test_a_tiny_cli_study_collects_once_and_refits_per_sampled_setting(counted, tmp_path):
    config = tmp_path / "td3.yml"
    config.write_text(yaml.safe_dump({TOY: dict(TINY)}))
    storage = f"sqlite:///{tmp_path}/s.db"
    argv = ["tune", "--config", str(config), "--env", TOY, "--study-name", "s", "--storage", storage, "--tune-algo",
            "--n-trials", "2", "--eval-episodes", "1", "--evaluations", "1"]  # fmt: skip
    assert main(argv) == 0
    first, second = optuna.load_study(study_name="s", storage=storage).trials
    assert first.state == second.state == TrialState.COMPLETE
    # another learning rate and batch: the second trial re-fits, on the first trial's demonstrations
    assert [first.user_attrs["pretrain"]["cache"], second.user_attrs["pretrain"]["cache"]] == [
        "none", "demonstrations"
    ]
    folder = default_cache_folder(storage, "s")
    assert folder == tmp_path / "s.pretrain"
    assert len(list(folder.glob("demonstrations-*.npz"))) == 1 and len(list(folder.glob("clone-*.pt"))) == 2
    assert len(counted) == 40


def test_a_bad_expert_is_one_line_before_any_trial(tmp_path, capsys):
    config = tmp_path / "td3.yml"
    config.write_text(yaml.safe_dump({TOY: {**TINY, "pretrain_from": "aim"}}))
    argv = ["tune", "--config", str(config), "--env", TOY, "--study-name", "s", "--storage",
            f"sqlite:///{tmp_path}/s.db", "--tune-algo", "--n-trials", "1"]  # fmt: skip
    assert main(argv) == 2
    err = capsys.readouterr().err.strip()
    assert "pretrain_from" in err and "'exact'" in err and len(err.splitlines()) == 1
    assert not (tmp_path / "s.pretrain").exists()


def test_cache_files_are_written_atomically_and_never_replace_a_file(tmp_path):
    path = tmp_path / "cache" / "clone-x.pt"
    assert write_atomically(path, lambda file: file.write(b"new"))
    assert path.read_bytes() == b"new"
    assert not write_atomically(path, lambda file: file.write(b"other"))
    assert path.read_bytes() == b"new"
    assert [p.name for p in path.parent.iterdir()] == ["clone-x.pt"]  # no temporary left behind
    assert default_cache_folder("journal://runs/j.log", "a") == tmp_path.__class__("runs/a.pretrain")
    assert str(default_cache_folder("postgresql://u@h/db", "a")) == "studies/a.pretrain"


def test_dagger_demonstrations_depend_on_the_learner_that_chose_the_states():
    """With one round the expert alone acts, so the labelled states do not depend on the learner's settings;
    with DAgger rounds the learner acts too, so its cloning steps enter the demonstrations' key (a cache
    labelled by another learner is not read)."""
    from sb3_graph.tuning.pretrain import demonstrations_key

    one = {"pretrain_from": "glide", "pretrain_transitions": 100}
    dagger = {**one, "pretrain_rounds": 3, "pretrain_beta": 0.5}
    for entry, differs in ((one, False), (dagger, True)):
        short, long = ({**entry, "pretrain_steps": steps} for steps in (2000, 10000))
        same = demonstrations_key(short, "E", "td3") == demonstrations_key(long, "E", "td3")
        assert same != differs
    assert demonstrations_key(dagger, "E", "td3") != demonstrations_key(dagger, "E", "sac")


def test_an_expert_with_other_settings_labels_again(monkeypatch, tmp_path):
    """An expert's ``cache_key`` (a search's parameters, whose defaults may change) enters the cache's keys: a cache
    labelled with other settings is never read, while the same settings are."""
    import sb3_graph.tuning.pretrain as pretrain

    calls = []

    def make_expert(spec, env, key):
        def expert(obs):
            calls.append(key)
            return toy_envs.max_neighbour_expert(obs)

        expert.cache_key = key
        return expert

    def clone(key):
        monkeypatch.setattr(toy_envs, "make_expert", lambda spec, env: make_expert(spec, env, key))
        config = settings(tmp_path / "cache")
        study = optuna.create_study(direction="maximize")
        study.optimize(lambda trial: run_trial(trial, config), n_trials=1)
        return study.trials[0].user_attrs["pretrain"]["cache"]

    assert pretrain._expert_settings(object()) == {}
    assert clone("search A") == "none" and clone("search A") == "clone"
    assert clone("search B") == "none"  # other settings: labelled again, the first files untouched
    assert len(list((tmp_path / "cache").glob("demonstrations-*"))) == 2
