"""``sb3-graph tune`` / ``tune-report``: search space, objectives, trials, failures, report, resume."""

import math

import numpy as np
import optuna
import pandas as pd
import pytest
import torch as th
import yaml
from optuna.trial import TrialState

from envs.simulation.env import CoopIntersectionEnv
from sb3_graph.cli import main
from sb3_graph.tuning.objectives import COLLISION, DELAY, FLOW, STOP, check_metrics, make_objective
from sb3_graph.tuning.pruners import evaluation_steps
from sb3_graph.tuning.report import first_rung_study, pruning_summary, trials_table, write_figures
from sb3_graph.tuning.runner import TrialSettings, resolve_callable, run_trial
from sb3_graph.tuning.search_space import (
    ALGO_SPACE,
    entry_with_params,
    sample_algo,
    sample_reward_weights,
    split_params,
)
from sb3_graph.tuning.toy import evaluate_max_neighbour

th.set_num_threads(1)
optuna.logging.set_verbosity(optuna.logging.WARNING)
TABLE_I = {"velocity": 0.03, "action": 0.01, "idle": 0.01, "proximity": 0.2, "collision": 1.0}
TINY = {
    "n_timesteps": 300,
    "policy": "GraphPolicy",
    "learning_starts": 50,
    "batch_size": 16,
    "buffer_size": 1000,
    "train_freq": 4,
    "policy_kwargs": "dict(encoder_dim=8, conv_dims=[8])",
}
INTERSECTION = "CoopIntersection4Way-v0"
TOY = "GraphMaxNeighbour-v0"


@pytest.fixture
def config(tmp_path):
    path = tmp_path / "td3.yml"
    entry = {**TINY, "env_kwargs": {"config": {"duration": 30.0}}}
    path.write_text(yaml.safe_dump({INTERSECTION: entry, TOY: dict(TINY)}))
    return path


def tune(config, study, *extra):
    return main(["tune", "--config", str(config), "--study-name", study, *extra])


# ---------------------------------------------------------------- search space and objectives
def test_weights_are_sampled_on_log_scales_around_their_defaults():
    study = optuna.create_study()
    for _ in range(20):
        trial = study.ask()
        weights = sample_reward_weights(trial, {**TABLE_I, "off": 0.0}, spread=10.0)
        assert set(weights) == set(TABLE_I)  # a zero weight has no log scale: not tuned
        for term, value in weights.items():
            assert TABLE_I[term] / 10 <= value <= TABLE_I[term] * 10
            assert trial.distributions[f"weight.{term}"].log
        study.tell(trial, 0.0)
    with pytest.raises(ValueError, match="spread"):
        sample_reward_weights(study.ask(), TABLE_I, spread=1.0)


def test_algo_settings_are_entry_keys():
    trial = optuna.create_study().ask()
    values = sample_algo(trial)
    assert set(values) == set(ALGO_SPACE)
    assert all(f"algo.{key}" in trial.params for key in values)


def test_params_go_into_the_entry_without_changing_it():
    entry = {"n_timesteps": 10, "env_kwargs": {"config": {"duration": 60.0, "reward_weights": {"idle": 0.5}}}}
    params = {"weight.velocity": 0.1, "algo.learning_rate": 0.002, "algo.noise_std": 0.3}
    new = entry_with_params(entry, params)
    assert new["env_kwargs"]["config"] == {"duration": 60.0, "reward_weights": {"idle": 0.5, "velocity": 0.1}}
    assert new["learning_rate"] == 0.002 and new["noise_std"] == 0.3 and new["noise_type"] == "normal"
    assert entry["env_kwargs"]["config"]["reward_weights"] == {"idle": 0.5}
    assert split_params(params) == ({"velocity": 0.1}, {"learning_rate": 0.002, "noise_std": 0.3})
    with pytest.raises(ValueError, match="'lr'"):
        split_params({"lr": 0.1})


def test_objectives():
    metrics = {FLOW: 0.5, COLLISION: 0.05, STOP: 0.2, DELAY: 10.0}
    flow = make_objective("flow", max_collision_rate=0.02)
    assert flow.values(metrics) == 0.5 and flow.prunable
    assert flow.constraint(metrics) == pytest.approx(0.03)  # > 0: infeasible
    assert isinstance(flow.pruner(), optuna.pruners.MedianPruner)
    assert isinstance(flow.pruner("successive-halving", 900), optuna.pruners.SuccessiveHalvingPruner)
    assert isinstance(flow.pruner("hyperband", 900), optuna.pruners.HyperbandPruner)
    assert isinstance(flow.pruner("none"), optuna.pruners.NopPruner)
    with pytest.raises(ValueError, match="pruner must be one of"):
        flow.pruner("asha")
    # flow with a delay or a stop term: one value, prunable, under the same collision constraint
    delay = make_objective("flow-delay", weight=0.02)
    assert delay.values(metrics) == pytest.approx(0.5 - 0.02 * 10.0) and delay.prunable
    assert delay.labels == ("flow_rate - 0.02 * delay_mean",) and delay.required() == (FLOW, DELAY, COLLISION)
    assert make_objective("flow-delay").values(metrics) == pytest.approx(0.5 - 0.01 * 10.0)  # default weight
    stop = make_objective("flow-stop")
    assert stop.values(metrics) == pytest.approx(0.5 - 0.2 * 0.2) and stop.constraint(metrics) == pytest.approx(0.03)
    assert isinstance(stop.sampler(), optuna.samplers.TPESampler)
    # pareto: flow up, delay down, stops down, with the constraint
    pareto = make_objective("pareto")
    assert pareto.values(metrics) == (0.5, 10.0, 0.2) and pareto.labels == (FLOW, DELAY, STOP)
    assert pareto.directions == ("maximize", "minimize", "minimize")
    assert not pareto.prunable and isinstance(pareto.pruner(), optuna.pruners.NopPruner)
    assert isinstance(pareto.sampler(), optuna.samplers.NSGAIISampler)
    assert pareto.constraint(metrics) == pytest.approx(0.03)
    with pytest.raises(ValueError, match="objective must be one of"):
        make_objective("fast")
    with pytest.raises(ValueError, match="max_collision_rate"):
        make_objective("flow", max_collision_rate=2.0)
    with pytest.raises(ValueError, match="takes no weight"):
        make_objective("flow", weight=0.1)
    with pytest.raises(ValueError, match="finite number >= 0"):
        make_objective("flow-stop", weight=-1.0)
    assert "no ['delay_mean']" in check_metrics({FLOW: 1.0, COLLISION: 0.0, STOP: 0.0}, pareto)
    assert "non-finite" in check_metrics({FLOW: math.nan, COLLISION: 0.0}, flow)
    assert check_metrics(metrics, pareto) is None


def test_resolve_callable():
    assert resolve_callable("sb3_graph.tuning.toy:evaluate_max_neighbour") is evaluate_max_neighbour
    with pytest.raises(ValueError, match="module:function"):
        resolve_callable("sb3_graph.tuning.toy.evaluate_max_neighbour")
    with pytest.raises(ValueError, match="cannot import"):
        resolve_callable("sb3_graph.tuning.toy:missing")


# ---------------------------------------------------------------- the intersection domain's pieces
def test_tuning_preset_and_evaluator_give_task_metrics():
    import gymnasium as gym

    import envs  # noqa: F401
    from envs.evaluation.tuning import PRESET_NAME, evaluate_model, tuning_env_kwargs
    from sb3_graph import TD3

    kwargs = tuning_env_kwargs()
    env = gym.make(INTERSECTION, **kwargs)
    full = env.unwrapped.default_config()
    config = env.unwrapped.config
    assert PRESET_NAME == "tuning"
    assert config["duration"] < full["duration"] and config["max_vehicles"] < full["max_vehicles"]
    assert config["layout"] == full["layout"] and config["reward_weights"] == full["reward_weights"]
    model = TD3("GraphPolicy", env, policy_kwargs={"encoder_dim": 8, "conv_dims": [8]}, seed=0)
    first = evaluate_model(model, INTERSECTION, kwargs, episodes=2, seed=3, duration=20.0)
    again = evaluate_model(model, INTERSECTION, kwargs, episodes=2, seed=3, duration=20.0)
    assert first == pytest.approx(again, nan_ok=True)  # the same validation episodes for every trial
    assert first["vehicles"] > 0 and first[FLOW] >= 0
    assert 0 <= first[COLLISION] <= 1 and 0 <= first[STOP] <= 1
    # changing the reward weights does not change the task metrics of the same model
    heavy = {"config": {**kwargs["config"], "reward_weights": {"collision": 100.0}}}
    assert evaluate_model(model, INTERSECTION, heavy, episodes=2, seed=3, duration=20.0) == pytest.approx(
        first, nan_ok=True
    )


# The weights a study tunes: the environment's own defaults (the task preset's).
DEFAULT_WEIGHTS = CoopIntersectionEnv.default_config()["reward_weights"]


# ---------------------------------------------------------------- whole studies
def test_tiny_study_on_sqlite_completes_reports_and_resumes(config, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    args = ["--env", INTERSECTION, "--n-trials", "2", "--timesteps", "300", "--evaluations", "2",
            "--eval-episodes", "2", "--max-collision-rate", "1.0", "--sampler-seed", "0"]  # fmt: skip
    assert tune(config, "weights", *args) == 0
    storage = "sqlite:///studies/weights.db"  # the default storage of the study
    study = optuna.load_study(study_name="weights", storage=storage)
    trials = study.get_trials()
    assert [t.state for t in trials] == [TrialState.COMPLETE] * 2
    for trial in trials:
        assert {f"weight.{term}" for term in DEFAULT_WEIGHTS} == set(trial.params)
        for metric in (FLOW, COLLISION, STOP):
            assert np.isfinite(trial.user_attrs[metric])
        assert trial.value == trial.user_attrs[FLOW]  # the task metric, not the training reward
        assert trial.intermediate_values == {150: pytest.approx(trial.intermediate_values[150]), 300: trial.value}
        assert trial.user_attrs["timesteps"] == 300
    assert study.user_attrs["entry"]["env_kwargs"] == {"config": {"duration": 30.0}}  # the full env, not the preset

    out = tmp_path / "report"
    assert main(["tune-report", "--study-name", "weights", "--storage", storage, "--out", str(out)]) == 0
    for name in ("best_params.yml", "trials.csv", "trials.md", "report.md", "optimization_history.png",
                 "param_importances.png", "pareto_front.png"):  # fmt: skip
        assert (out / name).is_file() and (out / name).stat().st_size > 0, name
    best = yaml.safe_load((out / "best_params.yml").read_text())[INTERSECTION]
    weights = best["env_kwargs"]["config"]["reward_weights"]
    assert weights == {term: study.best_trial.params[f"weight.{term}"] for term in DEFAULT_WEIGHTS}
    assert best["env_kwargs"]["config"]["duration"] == 30.0 and best["n_timesteps"] == TINY["n_timesteps"]
    assert len(pd.read_csv(out / "trials.csv")) == 2
    # a report never replaces files silently
    assert main(["tune-report", "--study-name", "weights", "--storage", storage, "--out", str(out)]) == 2

    # re-running the command resumes the study: the trials grow, the old ones are kept as they were
    assert tune(config, "weights", *args[:2], "--n-trials", "1", *args[4:]) == 0
    resumed = optuna.load_study(study_name="weights", storage=storage).get_trials()
    assert len(resumed) == 3 and resumed[2].state == TrialState.COMPLETE
    for old, new in zip(trials, resumed):
        assert (old.number, old.params, old.values, old.user_attrs) == (new.number, new.params, new.values,
                                                                        new.user_attrs)  # fmt: skip


def test_pareto_study_reports_its_front(config, tmp_path):
    storage = f"sqlite:///{tmp_path}/p.db"
    assert tune(config, "front", "--env", TOY, "--storage", storage, "--objective", "pareto", "--tune-algo",
                "--n-trials", "2", "--timesteps", "100", "--eval-episodes", "1") == 0  # fmt: skip
    study = optuna.load_study(study_name="front", storage=storage)
    assert len(study.directions) == 3 and len(study.trials) == 2
    assert all(len(t.values) == 3 and not t.intermediate_values for t in study.trials)  # no pruning
    out = tmp_path / "report"
    assert main(["tune-report", "--study-name", "front", "--storage", storage, "--out", str(out)]) == 0
    assert (out / "pareto_front.png").is_file() and (out / "best_params.yml").is_file()
    front = pd.read_csv(out / "pareto_front.csv")
    assert set(front["number"]) == {t.number for t in study.best_trials}


def toy_settings(evaluator, objective="flow", evaluations=1):
    return TrialSettings(
        env_id=TOY,
        entry={**TINY, "n_timesteps": 100},
        timesteps=100,
        objective=make_objective(objective, max_collision_rate=1.0),
        evaluator=evaluator,
        tune_algo=True,
        evaluations=evaluations,
        eval_episodes=1,
    )


def test_failing_and_diverging_trials_do_not_stop_the_study():
    import sb3_graph.toy_envs  # noqa: F401

    calls = []

    def flaky(model, **kwargs):
        calls.append(1)
        if len(calls) == 1:
            raise RuntimeError("simulator crashed")
        if len(calls) == 2:
            return {FLOW: math.nan, COLLISION: 0.0, STOP: 0.0}
        return evaluate_max_neighbour(model, **kwargs)

    study = optuna.create_study(direction="maximize")
    study.optimize(lambda t: run_trial(t, toy_settings(flaky)), n_trials=3, catch=(Exception,))
    failed, diverged, good = study.trials
    assert failed.state == TrialState.FAIL
    assert failed.user_attrs["reason"] == "RuntimeError: simulator crashed"
    assert "simulator crashed" in failed.user_attrs["traceback"]
    assert diverged.state == TrialState.PRUNED and diverged.user_attrs["reason"].startswith("diverged")
    assert good.state == TrialState.COMPLETE and FLOW in good.user_attrs


def test_intermediate_values_let_the_pruner_stop_a_trial():
    import sb3_graph.toy_envs  # noqa: F401

    study = optuna.create_study(direction="maximize", pruner=optuna.pruners.ThresholdPruner(lower=10.0))
    study.optimize(lambda t: run_trial(t, toy_settings(evaluate_max_neighbour, evaluations=4)), n_trials=1)
    trial = study.trials[0]
    assert trial.state == TrialState.PRUNED
    assert list(trial.intermediate_values) == [25]  # stopped at the first evaluation, not trained to the end
    assert trial.user_attrs["reason"].startswith("pruned at step 25")


def test_rungs_are_the_evaluation_steps_of_sha_and_hyperband():
    assert evaluation_steps("median", 300, 3) == (100, 200)
    assert evaluation_steps("none", 300, 1) == ()
    # 4 evaluations of a surviving trial: 3 rungs below the budget, the last one at the end
    assert evaluation_steps("successive-halving", 100_000, 4) == (3704, 11112, 33336)
    assert evaluation_steps("hyperband", 100_000, 3, reduction_factor=2) == (25_000, 50_000)
    assert evaluation_steps("hyperband", 1000, 3, min_resource=100, reduction_factor=3) == (100, 300, 900)
    with pytest.raises(ValueError, match="min resource must be in"):
        evaluation_steps("successive-halving", 100, 2, min_resource=100)


def test_successive_halving_stops_a_hopeless_trial_at_its_first_rung():
    """Toy setup: three trials of rising quality, then a hopeless one; SHA (rungs 25 and 50 of 100
    steps, halving) must stop the hopeless one at its first evaluation, after a quarter of its budget."""
    import sb3_graph.toy_envs  # noqa: F401

    quality, trained = [0.5], []

    def evaluator(model, **kwargs):
        trained.append(model.num_timesteps)
        return {FLOW: quality[0], COLLISION: 0.0, STOP: 0.0}

    settings = toy_settings(evaluator)
    settings.eval_steps = evaluation_steps("successive-halving", 100, 3, reduction_factor=2)
    assert settings.eval_steps == (25, 50)
    pruner = make_objective("flow").pruner("successive-halving", 100, 3, 25, reduction_factor=2)
    study = optuna.create_study(direction="maximize", pruner=pruner)
    for value in (0.5, 0.6, 0.7):  # each new trial the best so far: all promoted
        quality[0] = value
        study.optimize(lambda t: run_trial(t, settings), n_trials=1)
    assert [t.state for t in study.trials] == [TrialState.COMPLETE] * 3
    assert all(list(t.intermediate_values) == [25, 50, 100] for t in study.trials)
    quality[0], trained[:] = 0.0, []
    study.optimize(lambda t: run_trial(t, settings), n_trials=1)
    hopeless = study.trials[-1]
    assert hopeless.state == TrialState.PRUNED
    assert hopeless.intermediate_values == {25: 0.0}
    assert trained == [25]  # one evaluation, a quarter of the budget trained
    assert hopeless.user_attrs["reason"] == "pruned at step 25 (intermediate value 0)"
    # the report counts what pruning saved
    for key, value in {"pruner": "successive-halving", "timesteps": 100, "eval_steps": [25, 50]}.items():
        study.set_user_attr(key, value)
    table = trials_table(study)
    assert list(table["steps_trained"]) == [100, 100, 100, 25]
    assert pruning_summary(study, table) == (
        "- pruner: successive-halving, evaluations at steps [25, 50]; finished trials by steps trained: "
        "25: 1, 100: 3; 325 steps in all, 400 without pruning"
    )


def test_cli_pruner_flags_set_the_rungs_and_are_recorded(config, tmp_path):
    storage = f"sqlite:///{tmp_path}/sha.db"
    assert tune(config, "sha", "--env", TOY, "--storage", storage, "--tune-algo", "--n-trials", "2",
                "--timesteps", "120", "--eval-episodes", "1", "--pruner", "hyperband", "--min-resource", "60",
                "--reduction-factor", "2", "--trial-hyperparams", "n_envs:2", "train_freq:2") == 0  # fmt: skip
    study = optuna.load_study(study_name="sha", storage=storage)
    assert study.user_attrs["pruner"] == "hyperband" and study.user_attrs["eval_steps"] == [60]
    assert study.user_attrs["trial_hyperparams"] == {"n_envs": 2, "train_freq": 2}
    assert "n_envs" not in study.user_attrs["entry"]  # the report's zoo entry keeps the file's values
    for trial in study.trials:
        assert trial.state == TrialState.COMPLETE and set(trial.intermediate_values) <= {60, 120}


def test_user_errors_are_one_line_exit_2(config, tmp_path, capsys):
    db = f"sqlite:///{tmp_path}/e.db"
    base = ["--env", TOY, "--storage", db, "--tune-algo", "--timesteps", "100", "--n-trials", "1"]
    cases = [
        (["--objective", "fast"], "objective must be one of"),
        (["--storage", "mysql://u@h/db"], "accepted forms"),
        (["--timesteps", "50"], "learning_starts"),
        (["--evaluator", "nocolon"], "module:function"),
        (["--weight-spread", "1"], "--weight-spread must be > 1"),
        (["--env", "Nope-v0"], "no entry for env 'Nope-v0'"),
        (["--pruner", "asha"], "--pruner: unknown pruner 'asha'; allowed: median, successive-halving, hyperband"),
        (["--min-resource", "10"], "--min-resource applies to --pruner successive-halving or hyperband"),
        (["--pruner", "hyperband", "--min-resource", "100"], "--min-resource must be in [1, --timesteps 100)"),
        (["--pruner", "hyperband", "--reduction-factor", "1"], "--reduction-factor must be at least 2"),
        (["--pruner", "successive-halving", "--evaluations", "1"], "min resource must be in"),
        (["--trial-hyperparams", "n_envs"], "--trial-hyperparams: expected KEY:VALUE"),
        (["--trial-hyperparams", "n_envs:0"], "n_envs"),
    ]
    for extra, message in cases:
        assert tune(config, "e", *base, *extra) == 2
        assert message in capsys.readouterr().err
    assert main(["tune", "--config", str(config), "--env", TOY, "--study-name", "e", "--storage", db]) == 2
    assert "nothing to tune" in capsys.readouterr().err  # the toy env has no reward weights
    # a study made for one objective is not resumed with another
    assert tune(config, "e", *base, "--eval-episodes", "1") == 0
    assert tune(config, "e", *base, "--objective", "pareto") == 2
    assert "created with objective 'flow'" in capsys.readouterr().err
    assert main(["tune-report", "--study-name", "other", "--storage", db, "--out", str(tmp_path / "r")]) == 2
    assert "no study 'other'" in capsys.readouterr().err


def test_best_trial_prefers_feasible_trials_then_the_safest():
    from sb3_graph.tuning.report import best_trial

    study = optuna.create_study(direction="maximize")
    study.set_user_attr("max_collision_rate", 0.02)
    distribution = {"weight.velocity": optuna.distributions.FloatDistribution(0.003, 0.3, log=True)}

    def add(flow, collision):
        study.add_trial(
            optuna.trial.create_trial(
                value=flow,
                params={"weight.velocity": 0.03},
                distributions=distribution,
                user_attrs={FLOW: flow, COLLISION: collision},
                system_attrs={"constraints:collision_rate": collision - 0.02},
            )
        )

    add(1.0, 0.3)
    add(0.5, 0.1)
    trial, feasible = best_trial(study)
    assert (trial.number, feasible) == (1, False)  # none feasible: the lowest collision rate
    add(0.2, 0.0)
    add(0.1, 0.0)
    trial, feasible = best_trial(study)
    assert (trial.number, feasible) == (2, True)  # the best flow among the feasible ones


def test_a_study_whose_new_trials_all_failed_exits_non_zero_with_the_first_error(tmp_path, capsys):
    path = tmp_path / "typo.yml"
    path.write_text(yaml.safe_dump({TOY: {**TINY, "policy_kwargs": "dict(encoder_dims=8)"}}))  # typo: encoder_dims
    db = f"sqlite:///{tmp_path}/f.db"
    args = ["--env", TOY, "--storage", db, "--tune-algo", "--timesteps", "100", "--n-trials", "2"]
    assert tune(path, "f", *args) == 1
    err = capsys.readouterr().err
    assert "all 2 new trials failed" in err and "trial 0" in err and "encoder_dims" in err
    assert err.count("\n") == 1
    # a study with a good trial among the new ones exits 0
    path.write_text(yaml.safe_dump({TOY: dict(TINY)}))
    assert tune(path, "f", *args[:-1], "1") == 0


def test_importances_at_the_first_rung_use_pruned_trials_too(tmp_path):
    # Successive halving leaves one complete trial; the first rung (step 100) has all four.
    study = optuna.create_study(direction="maximize")
    dist = {"weight.idle": optuna.distributions.FloatDistribution(1e-3, 1e-1, log=True)}
    for k, (idle, first) in enumerate([(0.001, 0.0), (0.01, 0.1), (0.05, 0.2), (0.09, 0.3)]):
        state = TrialState.COMPLETE if k == 3 else TrialState.PRUNED
        steps = {100: first, 300: first + 0.1} if k >= 2 else {100: first}
        study.add_trial(
            optuna.trial.create_trial(
                params={"weight.idle": idle}, distributions=dist, intermediate_values=steps,
                state=state, value=first + 0.2 if state == TrialState.COMPLETE else None,
            )
        )  # fmt: skip
    rung = first_rung_study(study)
    assert rung.user_attrs["step"] == 100
    assert [t.value for t in rung.trials] == [0.0, 0.1, 0.2, 0.3]
    figures = write_figures(study, tmp_path)
    assert figures["param_importances"] == "needs at least 2 complete trials"
    assert figures["param_importances_first_rung"] == "param_importances_first_rung.png"
    assert (tmp_path / "param_importances_first_rung.png").stat().st_size > 0
    assert first_rung_study(optuna.create_study()) is None


def test_the_shipped_weight_study_holds_24_finished_trials_and_reports(tmp_path):
    # experiments/weight_study: the journal of the study of issue #15 and its report's zoo entry.
    from pathlib import Path

    folder = Path(__file__).resolve().parents[1] / "experiments" / "weight_study"
    storage = f"journal://{folder / 'weights_fair.log'}"
    study = optuna.load_study(study_name="weights_fair", storage=optuna.storages.JournalStorage(
        optuna.storages.journal.JournalFileBackend(str(folder / "weights_fair.log"))))  # fmt: skip
    finished = [t for t in study.trials if t.state in (TrialState.COMPLETE, TrialState.PRUNED)]
    assert len(finished) >= 24
    assert max(max(t.intermediate_values, default=0) for t in finished) >= 100_000
    assert (
        main(["tune-report", "--study-name", "weights_fair", "--storage", storage, "--out", str(tmp_path / "r")]) == 0
    )
    shipped = yaml.safe_load((folder / "best_params.yml").read_text())
    again = yaml.safe_load((tmp_path / "r" / "best_params.yml").read_text())
    # The shipped file predates the report's merge of the trials' --trial-hyperparams into the entry.
    env_id = "CoopIntersection4Way-v0"
    assert again[env_id] == {**shipped[env_id], **study.user_attrs["trial_hyperparams"]}
    weights = shipped["CoopIntersection4Way-v0"]["env_kwargs"]["config"]["reward_weights"]
    best = study.trials[0].params
    assert weights == {k.split(".", 1)[1]: v for k, v in best.items()}


def test_tune_trains_the_chosen_algorithm_with_its_search_space(config, tmp_path, capsys):
    from sb3_graph.files.policy_files import read_sb3_zip
    from sb3_graph.registry import ALGORITHMS

    storage, models = f"sqlite:///{tmp_path}/sac.db", tmp_path / "models"
    base = ["--env", TOY, "--storage", storage, "--tune-algo", "--n-trials", "1", "--timesteps", "100"]
    assert tune(config, "sac", *base, "--algo", "sac", "--eval-episodes", "1", "--save-models", str(models)) == 0
    study = optuna.load_study(study_name="sac", storage=storage)
    assert study.user_attrs["algo"] == "sac"
    (trial,) = study.trials
    assert trial.state == TrialState.COMPLETE
    assert set(trial.params) == {f"algo.{key}" for key in ALGORITHMS["sac"].tune_space}
    assert "algo.policy_delay" not in trial.params  # TD3's setting, not SAC's
    assert read_sb3_zip(models / "trial_0.zip")[0].algorithm == "SAC"
    assert tune(config, "sac", *base, "--eval-episodes", "1") == 2  # default --algo td3: another study
    assert "created with algo 'sac', not 'td3'" in capsys.readouterr().err


def test_the_shipped_shield_study_reports_what_its_trials_trained_with(tmp_path):
    # experiments/weight_study/shield_fine.log: issue #23's study behind the shield, fine-tuning the shipped planner.
    from pathlib import Path

    folder = Path(__file__).resolve().parents[1] / "experiments" / "weight_study"
    storage = f"journal://{folder / 'shield_fine.log'}"
    study = optuna.load_study(study_name="shield_fine", storage=optuna.storages.JournalStorage(
        optuna.storages.journal.JournalFileBackend(str(folder / "shield_fine.log"))))  # fmt: skip
    assert len([t for t in study.trials if t.state in (TrialState.COMPLETE, TrialState.PRUNED)]) >= 24
    assert study.user_attrs["init_weights"].endswith("coop_4way_fair/best_model.safetensors")
    assert main(["tune-report", "--study-name", "shield_fine", "--storage", storage, "--out", str(tmp_path / "r")]) == 0
    entry = yaml.safe_load((tmp_path / "r" / "best_params.yml").read_text())["CoopIntersection4Way-v0"]
    assert entry["learning_starts"] == 500  # the trials' --trial-hyperparams, not the file's 2000
    assert entry["env_kwargs"]["config"]["shield"] is True
    assert entry == yaml.safe_load((folder / "shield_fine" / "best_params.yml").read_text())["CoopIntersection4Way-v0"]


@pytest.mark.parametrize(
    "entry, extra, key, closest",
    [
        ({"learnig_rate": 0.001}, [], "learnig_rate", "learning_rate"),  # in the YAML entry
        ({}, ["--trial-hyperparams", "gama:0.9"], "gama", "gamma"),  # on the command line
    ],
)
def test_a_hyperparameter_typo_fails_before_the_first_trial(tmp_path, capsys, monkeypatch, entry, extra, key, closest):
    import sb3_graph.tuning.runner as runner

    def no_trial(*args, **kwargs):
        raise AssertionError("a trial ran")

    monkeypatch.setattr(runner, "run_trial", no_trial)
    path = tmp_path / "td3.yml"
    path.write_text(yaml.safe_dump({TOY: {**TINY, **entry}}))
    db = tmp_path / "typo.db"
    code = tune(path, "typo", "--env", TOY, "--storage", f"sqlite:///{db}", "--tune-algo", "--n-trials", "2", *extra)
    err = capsys.readouterr().err
    assert code == 2 and err.count("\n") == 1 and "Traceback" not in err, err
    assert f"{key}" in err and f"did you mean {closest!r}" in err and "TD3" in err
    assert not db.exists()  # refused before the study was opened: no trial, no storage
