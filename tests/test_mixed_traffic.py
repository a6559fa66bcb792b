"""Mixed traffic (issue 39): human drivers that the planner cannot command."""

from __future__ import annotations

import dataclasses
import json

import numpy as np
import pandas as pd
import pytest

from envs.evaluation.harness import evaluation_env_kwargs, run_episode
from envs.evaluation.metrics import run_metrics
from envs.planners import make_planner
from envs.planners.human import HumanDriver
from envs.simulation.env import CoopIntersectionEnv
from envs.simulation.graph import node_features
from envs.simulation.traffic import Scenario, demand_scenario, generate_scenario


def _rollout(config: dict, steps: int = 60, seed: int = 3) -> list[np.ndarray]:
    env = CoopIntersectionEnv(config)
    env.reset(seed=seed)
    rng = np.random.default_rng(0)
    states = []
    for _ in range(steps):
        env.step(rng.uniform(-1, 1, env.action_space.shape))
        states.append(np.concatenate([env.sim.vehicle_id, env.sim.arc, env.sim.speed]))
    return states


def test_share_zero_is_todays_behaviour_bit_for_bit():
    a, b = generate_scenario("4way", 120.0, 7), generate_scenario("4way", 120.0, 7, human_share=0)
    assert a.to_dict() == b.to_dict() and not b.human.any()
    base = {"spawn_probability": 0.2}
    for x, y in zip(_rollout(base), _rollout({**base, "human_share": 0.0})):
        assert np.array_equal(x, y)
    # A share only adds flags: the arrivals are drawn as before.
    c = generate_scenario("4way", 120.0, 7, human_share=0.5)
    assert np.array_equal(c.time, a.time) and c.route == a.route and np.array_equal(c.speed, a.speed)
    assert 0 < c.human.sum() < c.num_vehicles and c.meta["human_share"] == 0.5


def test_share_range_and_bad_values():
    s = demand_scenario("3way", 200.0, 1, 0.3, human_share=[0.2, 0.6])
    assert 0.2 <= s.meta["human_share"] <= 0.6
    assert generate_scenario("4way", 60.0, 2, human_share=1).human.all()
    for bad in (1.5, -0.1, [0.6, 0.2], "half", True, [0, 2]):
        with pytest.raises(ValueError, match=r"human_share.*\[0, 1\]"):
            CoopIntersectionEnv({"human_share": bad})
        with pytest.raises(ValueError, match=r"human_share.*\[0, 1\]"):
            generate_scenario("4way", 60.0, 2, human_share=bad)
    env = CoopIntersectionEnv({"human_share": [0.5, 1.0], "spawn_probability": 0.3})
    env.reset(seed=0)
    for _ in range(30):
        env.step(np.zeros(env.action_space.shape))
    assert 0.5 <= env.traffic.human_share <= 1.0 and env.sim.human.any()


def test_scenario_files_store_the_flag_and_old_files_are_all_automated(tmp_path):
    s = generate_scenario("4way", 60.0, 4, human_share=0.5)
    path = s.save(tmp_path / "s.json")
    data = json.loads(path.read_text())
    assert data["version"] == 2 and "human" in data["vehicles"][0]
    assert np.array_equal(Scenario.load(path).human, s.human)
    old = dict(data, version=1, vehicles=[{k: v for k, v in x.items() if k != "human"} for x in data["vehicles"]])
    (tmp_path / "old.json").write_text(json.dumps(old))
    loaded = Scenario.load(tmp_path / "old.json")
    assert loaded.num_vehicles == s.num_vehicles and not loaded.human.any()
    (tmp_path / "bad.json").write_text(json.dumps(dict(data, version=1)))
    with pytest.raises(ValueError, match="unknown fields.*human"):
        Scenario.load(tmp_path / "bad.json")
    data["vehicles"][0]["human"] = 1
    (tmp_path / "bad2.json").write_text(json.dumps(data))
    with pytest.raises(ValueError, match=r"vehicles\[0\].human must be true or false"):
        Scenario.load(tmp_path / "bad2.json")


def test_a_human_vehicle_ignores_the_planners_command():
    env = CoopIntersectionEnv({"spawn_probability": 0.0, "initial_spawn_probability": 0.0, "spawn_queue": 0})
    env.reset(seed=0)
    scene = env.place_vehicles(["west->east", "east->west"], arc=[20.0, 20.0], speed=[8.0, 8.0], human=[True, False])
    assert scene.human.tolist() == [True, False]
    assert node_features(scene, vertex_feature_names=["human"])[:, -1].tolist() == [1.0, 0.0]
    expected = HumanDriver().act(scene.copy())[0]
    env.step(env.accelerations_to_action(np.array([-5.0, -5.0])))  # both told to brake hard
    speed = env.sim.speed
    assert speed[1] == pytest.approx(8.0 - 5.0 * 0.2)  # the automated vehicle obeyed
    assert speed[0] == pytest.approx(max(8.0 + expected * 0.2, 0.0), abs=1e-3)  # the human drove on its own
    assert speed[0] > 7.5


def _run(spec: str, scenario: Scenario) -> tuple[pd.DataFrame, dict]:
    env = CoopIntersectionEnv(evaluation_env_kwargs({})["config"])
    vehicles, facts = run_episode(env, make_planner(spec), scenario, scenario.duration, seed=0)
    return vehicles, run_metrics(vehicles, facts["duration"])


@pytest.mark.parametrize(
    "spec", ["fullthrottle", "fifo", pytest.param("glide+shield", marks=pytest.mark.slow)]
)
def test_with_only_human_drivers_every_planner_equals_pr(spec):
    scenario = generate_scenario("4way", 40.0, 11, human_share=1.0)
    automated = Scenario(**{**scenario.__dict__, "human": np.zeros(scenario.num_vehicles, bool)})
    _, pr = _run("pr", automated)
    vehicles, row = _run(spec, scenario)
    assert vehicles["human"].all()
    for key in ("crossed", "flow_rate", "delay_mean", "stop_ratio_all", "collided"):
        assert row[key] == pytest.approx(pr[key], nan_ok=True), key
    assert row["flow_rate_human"] == row["flow_rate"] and row["vehicles_automated"] == 0


def test_metrics_split_automated_and_human():
    scenario = generate_scenario("4way", 40.0, 5, human_share=0.5)
    vehicles, row = _run("fifo", scenario)
    assert row["vehicles_automated"] + row["vehicles_human"] == row["vehicles"]
    assert row["vehicles_human"] == int(vehicles["human"].sum()) > 0
    assert row["flow_rate_automated"] + row["flow_rate_human"] == pytest.approx(row["flow_rate"])
    assert row["collisions_automated"] + row["collisions_human"] == row["collided"]


def _cut_in(aware: bool) -> tuple[int, dict[int, float]]:
    """A human on the major road (precedence) and an automated vehicle on the minor road driven at
    full throttle behind the shield, both 30 m before their lines at 10 m/s."""
    env = CoopIntersectionEnv(
        {"spawn_probability": 0.0, "initial_spawn_probability": 0.0, "spawn_queue": 0, "collision_handling": "remove"}
    )
    env.reset(seed=0)
    lay = env.layout
    entry = [lay.entry_arc[lay.route_id(r)] for r in ("west->east", "south->north")]
    env.place_vehicles(
        ["west->east", "south->north"], np.array(entry) - 30.0, [10.0, 10.0], vehicle_id=[1, 2], human=[True, False]
    )
    shield = make_planner("fullthrottle+shield")
    shield.reset(0)
    collisions, crossed = 0, {}
    for _ in range(60):
        scene = env.scene()
        seen = scene if aware else dataclasses.replace(scene, human=None)  # blind: takes the human for automated
        _, _, _, _, info = env.step(env.accelerations_to_action(shield.act(seen.copy())))
        collisions += len(info["record"].collisions)
        crossed.update(dict.fromkeys(info["record"].crossed.tolist(), info["record"].time))
    return collisions, crossed


def test_the_shield_keeps_an_automated_vehicle_from_cutting_in_front_of_a_human():
    collisions, crossed = _cut_in(aware=True)
    assert collisions == 0 and crossed[1] < crossed[2]  # the human went first, the automated one waited
    assert _cut_in(aware=False)[0] > 0  # a shield that took the human for commandable lets them collide


TINY = ["--scenarios", "1", "--duration", "20", "--seed", "2", "--jobs", "1", "--no-progress"]


def test_the_penetration_sweep_writes_the_share_column_and_figure(tmp_path, capsys):
    from sb3_graph.cli import main

    out = tmp_path / "sweep"
    args = ["sweep", "--planner", "pr", "--planner", "fifo", "--human-share", "1", "0", "--out", str(out)]
    assert main([*args, *TINY]) == 0
    assert "  human share 0: " in capsys.readouterr().out
    table = pd.read_csv(out / "sweep.csv")
    assert list(table.columns[:2]) == ["planner", "human_share"]
    assert {"collisions_automated", "collisions_human"} <= set(table.columns) and "demand" not in table
    assert sorted(set(table["human_share"])) == [0.0, 1.0]
    assert (out / "sweep.png").stat().st_size > 10_000 and "Penetration sweep" in (out / "sweep.md").read_text()
    for share in (0, 1):
        scenario = Scenario.load(next((out / f"human_share_{share}" / "scenarios").iterdir()))
        assert scenario.human.all() if share else not scenario.human.any()
    # Only human drivers: FIFO's runs are PR's.
    everyone = table[table["human_share"] == 1].set_index("planner")
    for column in ("flow_rate", "delay_mean_s", "stop_ratio", "collision_rate"):
        assert everyone.loc["FIFO", column] == pytest.approx(everyone.loc["PR", column], nan_ok=True), column
    # No human driver: the figures of a plain evaluation on the same seeds.
    assert main(["evaluate", "--planner", "fifo", "--out", str(tmp_path / "plain"), *TINY]) == 0
    plain = json.loads((tmp_path / "plain" / "summary.json").read_text())["FIFO"]
    none = table[(table["human_share"] == 0) & (table["planner"] == "FIFO")].iloc[0]
    assert none["flow_rate"] == plain["flow_rate"]["mean"] and none["delay_mean_s"] == plain["delay_s"]["mean"]
    assert main(["evaluate", "--planner", "fifo", "--human-share", "0.5", "--out", str(tmp_path / "half"), *TINY]) == 0
    half = Scenario.load(next((tmp_path / "half" / "scenarios").iterdir()))
    assert 0 < half.human.sum() < half.num_vehicles


@pytest.mark.parametrize(
    "extra, message",
    [
        (["--human-share", "1.5"], "--human-share: each share must be in [0, 1]"),
        (["--human-share", "0", "0"], "--human-share: a share is given twice"),
        (["--human-share", "0", "1", "--demand", "0.1", "0.2"], "--demand: with --human-share, give at most one"),
    ],
)
def test_bad_shares_are_one_line_errors(tmp_path, capsys, extra, message):
    from sb3_graph.cli import main

    out = tmp_path / "sweep"
    assert main(["sweep", "--planner", "pr", *extra, "--out", str(out), *TINY]) == 2
    err = capsys.readouterr().err.strip()
    assert message in err and len(err.splitlines()) == 1 and not out.exists()


@pytest.mark.parametrize("spec, share", [("glide+shield", 0.25), ("fullthrottle+shield", 0.5)])
def test_the_shield_keeps_automated_vehicles_from_running_into_a_slowing_human(spec, share):
    # The 4-way penetration sweep's scenario 4: without the cap behind humans, glide+shield ran into a
    # human slowing for its turn (0.25) and full throttle into an automated vehicle braking behind one (0.5).
    scenario = generate_scenario("4way", 60.0, 4, human_share=share)
    _, row = _run(spec, scenario)
    assert row["collided"] == 0 and row["crossed"] > 10


def test_an_automated_vehicle_yields_before_merging_beside_a_human():
    # inD at share 0.25, seed 4 (the penetration sweep's scenario 4): a human on the major road and an
    # automated right-turner reach the east exit side by side. A shield that predicted the human keeping
    # a gap to the merging vehicle let the automated one in, found no safe plan, braked it in front of
    # the human and the human ran into it (the human's model sees it only once it leads on its lane).
    from envs.simulation.env import CoopIntersectionInDEnv

    env = CoopIntersectionInDEnv(evaluation_env_kwargs({})["config"])
    scenario = generate_scenario(env.layout, 60.0, 4, human_share=0.25)
    shield = make_planner("glide+shield")
    vehicles, _ = run_episode(env, shield, scenario, scenario.duration, seed=0)
    assert vehicles["human"].any() and not vehicles["collided"].any()
    assert shield.unresolved == 0
