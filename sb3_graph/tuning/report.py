"""The report of a study: best parameters as a zoo YAML entry, a table of trials, figures (PNG).

Files written by :func:`write_report` into the output folder:

- ``best_params.yml``: a ready rl-zoo3 entry (``{env_id: entry}``): the study's experiment entry as
  read from ``--config`` (the full environment, not the tuning preset) with the best trial's
  weights in ``env_kwargs.config.reward_weights`` and its TD3 settings. Best: for ``flow`` the
  feasible trial (collision rate within the limit) with the highest flow rate; for ``pareto`` the
  Pareto-front trial with the highest flow rate among those within the collision limit. When no
  trial meets the limit, the one with the lowest collision rate, with a warning in the file.
- ``trials.csv`` and ``trials.md``: one row per trial (state, values, parameters, metrics, reason).
- ``pareto_front.csv`` (pareto): the trials of the front.
- ``optimization_history.png``, ``param_importances.png`` (PED-ANOVA, Optuna's default),
  ``param_importances_first_rung.png`` (flow: the importances for the validation flow at the first
  evaluation, which pruned trials reached too; a pruned study may have too few complete trials),
  ``intermediate_values.png`` (flow), ``pareto_front.png`` (pareto: the 3-objective front;
  flow: flow rate against collision rate with the limit), made with ``optuna.visualization.matplotlib``.
- ``report.md``: a summary that links all of the above and says why a figure is missing.
"""

from __future__ import annotations

import math
import warnings
from pathlib import Path
from typing import Any

import numpy as np
import optuna
import pandas as pd
import yaml
from optuna.trial import FrozenTrial, TrialState

from sb3_graph.tuning.objectives import COLLISION, FLOW
from sb3_graph.tuning.search_space import entry_with_params, split_params

METRIC_COLUMNS = (
    "flow_rate",
    "collision_rate",
    "stop_ratio",
    "stop_ratio_major",
    "stop_ratio_minor",
    "delay_mean",
    "shield_intervention_rate",
)
FIGURES = (
    "optimization_history",
    "param_importances",
    "param_importances_first_rung",
    "intermediate_values",
    "pareto_front",
)


def _number(value: Any) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool) and not math.isnan(value)


def _text(value: Any) -> bool:
    return isinstance(value, str) and len(value) <= 10_000


# The attributes a report reads, what each must be (a study is a file or database from others).
STUDY_ATTRS: dict[str, tuple[Any, str]] = {
    "metrics": (lambda v: isinstance(v, list) and all(_text(x) for x in v), "a list of strings"),
    "timesteps": (lambda v: _number(v) and v >= 0 and float(v).is_integer() and v < 2**53, "an integer >= 0"),
    "max_collision_rate": (lambda v: _number(v) and math.isfinite(v), "a finite number"),
    "entry": (lambda v: isinstance(v, dict) and all(isinstance(k, str) for k in v), "a mapping"),
    "env": (_text, "a string"),
    "pruner": (_text, "a string"),
    "objective": (_text, "a string"),
    "eval_steps": (lambda v: isinstance(v, list) and all(_number(x) for x in v), "a list of numbers"),
    "init_weights": (_text, "a string"),
}
TRIAL_ATTRS: dict[str, tuple[Any, str]] = {
    **{name: (_number, "a number") for name in METRIC_COLUMNS},
    "timesteps": (_number, "a number"),
    "step": (lambda v: _number(v) and float(v).is_integer(), "an integer"),
    "reason": (_text, "a string"),
    "worker": (lambda v: _text(v) or _number(v), "a string or a number"),
}


def check_study(study: optuna.Study) -> None:
    """Check the attributes that the report reads, so that a study from elsewhere fails in one line.

    :param study: the study
    :raises ValueError: ``study <name>: user attribute <key> must be <allowed>, got <value>``
    """
    where = f"study {study.study_name!r}"

    def check(attrs: dict[str, Any], rules: dict[str, tuple[Any, str]], owner: str) -> None:
        for key, (rule, allowed) in rules.items():
            if key in attrs and not rule(attrs[key]):
                raise ValueError(f"{owner}: user attribute {key!r} must be {allowed}, got {str(attrs[key])[:80]!r}")

    check(study.user_attrs, STUDY_ATTRS, where)
    for trial in study.get_trials(deepcopy=False):
        check(trial.user_attrs, TRIAL_ATTRS, f"{where}, trial {trial.number}")
        try:
            split_params(trial.params)
        except (TypeError, ValueError) as error:
            raise ValueError(f"{where}, trial {trial.number}: {error}") from None
        constraints = [v for k, v in trial.system_attrs.items() if k == "constraints" or k.startswith("constraints:")]
        flat = [c for v in constraints for c in (v if isinstance(v, list) else [v])]
        if not all(_number(c) for c in flat):
            raise ValueError(f"{where}, trial {trial.number}: system attribute 'constraints' must hold numbers")


def _metrics(study: optuna.Study) -> list[str]:
    names = study.user_attrs.get("metrics")
    if names and len(names) == len(study.directions):
        return list(names)
    return ["value"] if len(study.directions) == 1 else [f"value_{i}" for i in range(len(study.directions))]


def trials_table(study: optuna.Study) -> pd.DataFrame:
    """One row per trial: number, state, objective values, parameters, metrics, reason, worker, duration.

    :param study: the study
    :return: the table (objective columns are named ``objective:<metric>``)
    """
    names = _metrics(study)
    rows = []
    for trial in study.get_trials(deepcopy=False):
        row: dict[str, Any] = {"number": trial.number, "state": trial.state.name}
        values = trial.values or [math.nan] * len(names)
        row.update({f"objective:{name}": value for name, value in zip(names, values)})
        row.update(trial.params)
        row.update({name: trial.user_attrs.get(name, math.nan) for name in METRIC_COLUMNS})
        constraints = trial.system_attrs.get("constraints") or [
            value for key, value in trial.system_attrs.items() if key.startswith("constraints:")
        ]
        row["feasible"] = bool(constraints) and all(c <= 0 for c in constraints) if constraints else None
        row["steps_trained"] = _steps_trained(trial)
        row["reason"] = trial.user_attrs.get("reason", "")
        row["worker"] = trial.user_attrs.get("worker", "")
        row["duration_s"] = trial.duration.total_seconds() if trial.duration is not None else math.nan
        rows.append(row)
    return pd.DataFrame(rows)


def _steps_trained(trial: FrozenTrial) -> float:
    """Training steps a trial ran: its last reported step (a pruned trial stopped there), else its budget."""
    if trial.last_step is not None:
        return float(trial.last_step)
    if trial.state == TrialState.COMPLETE:
        return float(trial.user_attrs.get("timesteps", math.nan))
    return math.nan


def pruning_summary(study: optuna.Study, table: pd.DataFrame) -> str:
    """One line: the pruner, how many trials stopped at each step, and the steps saved by stopping early."""
    pruner = study.user_attrs.get("pruner", "?")
    budget = study.user_attrs.get("timesteps")
    finished = table[table["state"].isin(("COMPLETE", "PRUNED"))]
    steps = finished["steps_trained"].dropna()
    if not len(steps) or not budget:
        return f"- pruner: {pruner}"
    counts = ", ".join(f"{int(step):,}: {n}" for step, n in sorted(steps.value_counts().items()))
    return (
        f"- pruner: {pruner}, evaluations at steps {study.user_attrs.get('eval_steps', [])}; finished trials by "
        f"steps trained: {counts}; {int(steps.sum()):,} steps in all, {len(steps) * int(budget):,} without pruning"
    )


def best_trial(study: optuna.Study) -> tuple[FrozenTrial | None, bool]:
    """The trial whose parameters the report recommends (see the module docstring).

    :param study: the study
    :return: ``(trial, feasible)``; when no complete trial meets the collision limit, the complete
        trial with the lowest collision rate (then the highest flow rate) and ``False``;
        ``(None, False)`` without complete trials
    """
    complete = [t for t in study.get_trials(deepcopy=False) if t.state == TrialState.COMPLETE]
    if not complete:
        return None, False
    limit = float(study.user_attrs.get("max_collision_rate", 0.0))

    def collision(t: FrozenTrial) -> float:
        return float(t.user_attrs.get(COLLISION, math.inf))

    def flow(t: FrozenTrial) -> float:
        return float(t.user_attrs.get(FLOW, -math.inf))

    if len(study.directions) == 1:
        try:
            return study.best_trial, True
        except ValueError:  # no feasible trial
            return min(complete, key=lambda t: (collision(t), -flow(t))), False
    front = study.best_trials
    feasible = [t for t in front if collision(t) <= limit]
    if feasible:
        return max(feasible, key=flow), True
    return min(front, key=lambda t: (collision(t), -flow(t))), False


def best_entry(study: optuna.Study, trial: FrozenTrial) -> dict[str, Any]:
    """``{env_id: entry}`` with the trial's parameters in the study's experiment entry, and the
    study's ``--trial-hyperparams`` that every trial trained with (e.g. a fine-tune's ``learning_starts``)."""
    entry = {**(study.user_attrs.get("entry") or {}), **(study.user_attrs.get("trial_hyperparams") or {})}
    env_id = study.user_attrs.get("env", "ENV_ID")
    return {env_id: entry_with_params(entry, trial.params)}


def markdown_table(frame: pd.DataFrame, digits: int = 4) -> str:
    """A GitHub markdown table (no ``tabulate`` dependency)."""

    def cell(value: Any) -> str:
        if isinstance(value, float):
            return "" if math.isnan(value) else f"{value:.{digits}g}"
        return str(value).replace("|", "\\|").replace("\n", " ")

    lines = ["| " + " | ".join(map(str, frame.columns)) + " |", "|" + "---|" * len(frame.columns)]
    lines += ["| " + " | ".join(cell(v) for v in row) + " |" for row in frame.itertuples(index=False)]
    return "\n".join(lines) + "\n"


def _save(ax: Any, path: Path) -> None:
    import matplotlib.pyplot as plt

    figure = ax.figure if hasattr(ax, "figure") else np.ravel(ax)[0].figure
    figure.set_size_inches(8, 5.5)
    figure.tight_layout()
    figure.savefig(path, dpi=110)
    plt.close(figure)


def write_figures(study: optuna.Study, out: Path) -> dict[str, str]:
    """Write the PNG figures; returns ``name -> file name or the reason it is missing``."""
    import matplotlib

    matplotlib.use("Agg")
    from optuna.visualization import matplotlib as ovm

    names = _metrics(study)
    single = len(study.directions) == 1
    complete = [t for t in study.get_trials(deepcopy=False) if t.state == TrialState.COMPLETE]
    target = None if single else (lambda t: t.values[0])
    target_name = names[0]
    plots = {
        "optimization_history": lambda: ovm.plot_optimization_history(study, target=target, target_name=target_name),
        "param_importances": lambda: ovm.plot_param_importances(study, target=target, target_name=target_name),
    }
    if single:
        rung = first_rung_study(study)
        plots["param_importances_first_rung"] = lambda: ovm.plot_param_importances(
            rung, target_name=f"{target_name} at step {rung.user_attrs['step']:,}"
        )
        plots["intermediate_values"] = lambda: ovm.plot_intermediate_values(study)
        plots["pareto_front"] = lambda: _flow_collision(study)
    else:
        plots["pareto_front"] = lambda: ovm.plot_pareto_front(study, target_names=names)
    results: dict[str, str] = {}
    for name, plot in plots.items():
        if name == "param_importances" and len(complete) < 2:
            results[name] = "needs at least 2 complete trials"
            continue
        if name == "param_importances_first_rung" and rung is None:
            results[name] = "no evaluation that two trials reached"
            continue
        if not complete and name not in ("intermediate_values", "param_importances_first_rung"):
            results[name] = "no complete trial"
            continue
        try:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")  # Optuna marks its matplotlib plots experimental
                ax = plot()
            _save(ax, out / f"{name}.png")
            results[name] = f"{name}.png"
        except (ValueError, RuntimeError, ZeroDivisionError) as error:  # e.g. parameters without variance
            results[name] = f"not drawn: {error}"
    return results


def first_rung_study(study: optuna.Study) -> optuna.Study | None:
    """An in-memory study whose trials are the study's trials (complete and pruned) valued at their
    first evaluation, the step most trials reported; ``None`` when fewer than two reached it.

    Optuna's importance evaluators read complete trials only; under successive halving most trials
    stop at the first rung, so this is where every trial has a comparable value.
    """
    trials = [
        t
        for t in study.get_trials(deepcopy=False)
        if t.state in (TrialState.COMPLETE, TrialState.PRUNED) and t.intermediate_values and t.params
    ]
    steps = [min(t.intermediate_values) for t in trials]
    if not steps:
        return None
    step = max(set(steps), key=lambda k: (steps.count(k), -k))
    reached = [t for t in trials if step in t.intermediate_values]
    if len(reached) < 2:
        return None
    rung = optuna.create_study(direction=study.direction)
    rung.set_user_attr("step", int(step))
    for t in reached:
        value = t.intermediate_values[step]
        rung.add_trial(optuna.trial.create_trial(params=t.params, distributions=t.distributions, value=value))
    return rung


def _flow_collision(study: optuna.Study):
    """Flow rate against collision rate of the complete trials, with the constraint (flow objective)."""
    import matplotlib.pyplot as plt

    table = trials_table(study)
    done = table[table["state"] == "COMPLETE"]
    limit = float(study.user_attrs.get("max_collision_rate", 0.0))
    _, ax = plt.subplots()
    feasible = done[done[COLLISION] <= limit]
    ax.scatter(done[COLLISION], done[FLOW], c="tab:gray", label="infeasible")
    ax.scatter(feasible[COLLISION], feasible[FLOW], c="tab:blue", label="feasible")
    for row in done.itertuples():
        ax.annotate(str(row.number), (getattr(row, COLLISION), getattr(row, FLOW)), fontsize=7)
    ax.axvline(limit, color="tab:red", linestyle="--", label=f"max collision rate {limit:g}")
    ax.set_xlabel("collision rate")
    ax.set_ylabel("flow rate [veh/s]")
    ax.set_title("Trials: flow rate vs collision rate")
    ax.legend()
    return ax


def write_report(study: optuna.Study, out: str | Path) -> list[Path]:
    """Write every report file of the study into ``out`` (created).

    :param study: the study
    :param out: output folder
    :return: the files written
    """
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    written = []
    table = trials_table(study)
    table.to_csv(out / "trials.csv", index=False)
    (out / "trials.md").write_text(markdown_table(table) if len(table) else "no trials\n")
    written += [out / "trials.csv", out / "trials.md"]
    best, feasible = best_trial(study)
    limit = study.user_attrs.get("max_collision_rate", "?")
    if best is not None:
        path = out / "best_params.yml"
        header = (
            f"# sb3-graph tune-report: study {study.study_name!r}, trial {best.number} "
            f"(values {best.values}); paste into the zoo config\n"
        )
        if not feasible:
            header += (
                f"# WARNING: no trial met the collision-rate limit {limit}; this one has the lowest collision rate\n"
            )
        path.write_text(header + yaml.safe_dump(best_entry(study, best), sort_keys=False))
        written.append(path)
    if len(study.directions) > 1 and len(table):
        front = {t.number for t in study.best_trials}
        path = out / "pareto_front.csv"
        table[table["number"].isin(front)].to_csv(path, index=False)
        written.append(path)
    figures = write_figures(study, out)
    written += [out / f for f in figures.values() if f.endswith(".png")]
    counts = ", ".join(f"{n} {s.lower()}" for s, n in table["state"].value_counts().items()) if len(table) else ""
    lines = [
        f"# Study `{study.study_name}`",
        "",
        f"- objective: {study.user_attrs.get('objective', '?')} ({', '.join(_metrics(study))}; "
        f"directions {[d.name.lower() for d in study.directions]})",
        f"- environment: {study.user_attrs.get('env', '?')}, {study.user_attrs.get('timesteps', '?')} steps per trial",
        f"- trials fine-tune {study.user_attrs['init_weights']} (`sb3-graph train --init-weights` with the zoo entry)"
        if study.user_attrs.get("init_weights")
        else "- trials train from scratch",
        f"- trials: {len(table)} ({counts})",
        pruning_summary(study, table) if len(table) else "- pruner: no trials",
        f"- best trial: {best.number} {best.params}" if best is not None else "- best trial: none (no complete trial)",
        ""
        if feasible or best is None
        else f"  (no trial met the collision-rate limit {limit}: lowest collision rate shown)",
        "",
        "## Figures",
        "",
    ]
    lines += [f"- {name}: ![{name}]({f})" if f.endswith(".png") else f"- {name}: {f}" for name, f in figures.items()]
    lines += ["", "## Trials", "", "See `trials.csv`; `best_params.yml` holds the ready zoo entry.", ""]
    (out / "report.md").write_text("\n".join(lines))
    written.append(out / "report.md")
    return written
