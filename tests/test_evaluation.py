"""The evaluation harness and the report writer, on a tiny stand-in environment."""

from __future__ import annotations

import json

import matplotlib.image
import numpy as np
import pandas as pd
import pytest

from envs.evaluation.harness import run_episode
from envs.evaluation.metrics import add_travel_times, run_metrics
from envs.evaluation.report import FIGURES, REPORT_FILES, write_report
from envs.planners import FIFOPlanner, PriorityRulesPlanner
from envs.simulation.scene import MAJOR, MINOR, STRAIGHT, Scene
from envs.simulation.step_record import StepRecord

SUMMARY_KEYS = {
    "runs", "vehicles", "vehicles_scheduled", "not_spawned", "flow_rate", "offered_flow", "stop_ratio",
    "collision_rate", "collided", "delay_s", "speed_limit_violations", "governor_share", "stuck_runs",
    "last_crossing_s", "slow_ratio", "hard_brakes_per_vehicle", "energy_kj_per_vehicle",
}  # fmt: skip


class CrossingStub:
    """Two vehicles on crossing paths, major 40 m and minor 15 m before their stop lines.

    Kinematics from the commanded accelerations; the step record (envs.simulation.step_record) in the info.
    """

    dt = 0.2
    inside = 20.0
    start = (40.0, 15.0)

    def __init__(self):
        self.unwrapped = self

    def reset(self, seed=None, options=None):
        self.time = 0.0
        self.dist = np.array(self.start)  # front to stop line
        self.speed = np.array([10.0, 10.0])
        self.ids = np.array([1, 2])
        self.done = np.zeros(2, bool)
        return {}, StepRecord(time=0.0, num_vehicles=2).info()

    def scene(self) -> Scene:
        keep = ~self.done
        n = int(keep.sum())
        return Scene(
            time=self.time,
            dt=self.dt,
            vehicle_id=self.ids[keep],
            route=np.array([0, 1])[keep],
            s=np.zeros(n),
            position=np.zeros((n, 2)),
            heading=np.zeros(n),
            speed=self.speed[keep],
            speed_limit=np.full(n, 10.0),
            dist_to_entry=self.dist[keep],
            dist_to_exit=self.dist[keep] + self.inside + 5.0,
            leader=np.full(n, -1),
            gap=np.full(n, np.inf),
            priority=np.array([MAJOR, MINOR])[keep],
            maneuver=np.full(n, STRAIGHT),
            length=np.full(n, 5.0),
            route_names=("south->north", "west->east"),
            conflicts=np.array([[0, 1], [1, 0]], bool),
        )

    def accelerations_to_action(self, acc):
        return np.asarray(acc, float)

    def step(self, action):
        keep = np.flatnonzero(~self.done)
        old_exit = self.dist + self.inside + 5.0
        self.speed[keep] = np.maximum(self.speed[keep] + action * self.dt, 0.0)
        self.dist[keep] -= self.speed[keep] * self.dt
        self.time += self.dt
        new_exit = self.dist + self.inside + 5.0
        crossed = self.ids[(old_exit > 0) & (new_exit <= 0) & ~self.done]
        inside = (self.dist < 0) & (new_exit > 0)
        collisions = np.array([[1, 2]]) if inside.all() else np.zeros((0, 2), np.int64)
        stopped = self.ids[~self.done & (self.speed < 0.3)]
        self.done |= new_exit < -30.0
        record = StepRecord(time=self.time, crossed=crossed, stopped=stopped, collisions=collisions)
        return None, 0.0, bool(len(collisions)), False, record.info()


@pytest.mark.parametrize("planner, first", [(PriorityRulesPlanner(), 1), (FIFOPlanner(), 2)])
def test_run_episode_no_collision_right_order(planner, first):
    """PR: the major-road vehicle crosses first and the minor one stops; FIFO: the closer one first."""
    vehicles, facts = run_episode(CrossingStub(), planner, scenario=None, duration=20.0, seed=0)
    assert facts["duration"] == pytest.approx(20.0) and facts["steps"] == 100 and not facts["terminated"]
    frame = vehicles.set_index("vehicle_id")
    assert not frame["collided"].any()
    assert frame["crossed"].notna().all()  # both got through
    assert frame.loc[first, "crossed"] < frame.loc[3 - first, "crossed"]
    assert not frame.loc[first, "stopped"]
    if isinstance(planner, PriorityRulesPlanner):
        assert frame.loc[2, "stopped"]


def test_run_episode_collision_when_nobody_yields():
    class Reckless(PriorityRulesPlanner):
        def act(self, scene):
            return np.zeros(scene.num_vehicles)

    class SameTime(CrossingStub):
        start = (40.0, 40.0)

    vehicles, facts = run_episode(SameTime(), Reckless(), scenario=None, duration=20.0)
    assert facts["terminated"] and facts["duration"] < 20.0
    assert run_metrics(vehicles, facts["duration"])["collision_rate"] == 1.0


def test_run_episode_needs_the_step_record():
    class Untyped(CrossingStub):
        def reset(self, seed=None, options=None):
            super().reset(seed, options)
            return {}, {"time": 0.0, "crossed": []}  # the documented keys, but no record

    with pytest.raises(TypeError, match="StepRecord under 'record'"):
        run_episode(Untyped(), FIFOPlanner(), scenario=None, duration=1.0)


def test_planner_counters_reach_the_metrics_row_through_stats(tmp_path):
    """Any planner's :meth:`~envs.planners.Planner.stats` become columns of its runs; the planner-error
    lines only come with a ``planner_errors`` counter (a shield's)."""
    from envs.evaluation.harness import Job, run_job
    from envs.simulation.traffic import generate_scenario

    (tmp_path / "counting.py").write_text(
        "from envs.planners import FIFOPlanner\n\n\n"
        "class Counting(FIFOPlanner):\n"
        "    def reset(self, seed=None):\n        super().reset(seed)\n        self.answered = 0\n\n"
        "    def act(self, scene):\n        self.answered += 1\n        return super().act(scene)\n\n"
        "    def stats(self):\n        return {'answered_scenes': self.answered}\n"
    )
    scenario = tmp_path / "scenario_000.json"
    generate_scenario("4way", 4.0, 0).save(scenario)
    rows = {}
    for spec in (f"{tmp_path / 'counting.py'}:Counting", "fifo", "fifo+shield"):
        rows[spec] = run_job(Job(spec, spec, str(scenario), 0, "CoopIntersection4Way-v0", 4.0, 0))[0]
    counting = rows[f"{tmp_path / 'counting.py'}:Counting"]
    assert counting["answered_scenes"] == counting["steps"] == 20 and "planner_error" not in counting
    assert not {"answered_scenes", "shield_interventions", "planner_error"} & set(rows["fifo"])
    shielded = rows["fifo+shield"]
    assert shielded["shield_vehicle_steps"] > 0 and shielded["planner_errors"] == 0
    assert "planner_error" in shielded and shielded["planner_error"] is None


def _fake_results():
    rng = np.random.default_rng(0)
    runs, vehicles = [], []
    for planner in ("PR", "FIFO"):
        for k in range(3):
            frame = pd.DataFrame(
                {
                    "vehicle_id": np.arange(10),
                    "route": "r",
                    "priority": ["major"] * 6 + ["minor"] * 4,
                    "maneuver": [
                        "left",
                        "straight",
                        "right",
                        "straight",
                        "straight",
                        "left",
                        "right",
                        "left",
                        "straight",
                        "straight",
                    ],
                    "first_seen": 0.0,
                    "path_length": 100.0,
                    "speed_limit": 10.0,
                    "crossed": np.where(rng.random(10) < 0.7, 10.0 + rng.random(10) * 10, np.nan),
                    "removed": np.nan,
                    "stopped": rng.random(10) < 0.5,
                    "collided": False,
                }
            )
            row = {"planner": planner, "scenario": f"scenario_{k:03d}.json"}
            row.update(run_metrics(frame, 100.0))
            runs.append(row)
            vehicles.append(frame.assign(planner=planner, scenario=row["scenario"]))
    return pd.DataFrame(runs), pd.concat(vehicles, ignore_index=True)


def test_write_report_files_and_schema(tmp_path):
    runs, vehicles = _fake_results()
    summary = write_report(tmp_path, runs, vehicles, {"environment": "stub"})
    for name in REPORT_FILES:
        assert (tmp_path / name).is_file(), name
    on_disk = json.loads((tmp_path / "summary.json").read_text())
    assert on_disk == json.loads(json.dumps(summary))
    assert set(on_disk) == {"PR", "FIFO"}
    for entry in on_disk.values():
        assert set(entry) == SUMMARY_KEYS
        assert set(entry["flow_rate"]) == {"median", "q1", "q3", "mean"}
        assert set(entry["stop_ratio"]) == {"all", "major", "minor", "left", "straight", "right"}
        assert set(entry["delay_s"]) == {"median", "mean"}
        assert isinstance(entry["runs"], int) and entry["runs"] == 3 and entry["vehicles"] == 30
    csv = pd.read_csv(tmp_path / "metrics.csv")
    assert len(csv) == 6 and {"planner", "scenario", "flow_rate", "collision_rate"} <= set(csv.columns)
    md = (tmp_path / "report.md").read_text()
    assert "| PR |" in md and "| FIFO |" in md
    for figure in FIGURES:
        image = matplotlib.image.imread(tmp_path / figure)
        assert image.shape[0] > 100 and image.shape[1] > 100


@pytest.mark.parametrize("name", ["pr", "fifo"])
def test_baselines_collision_free_and_live_on_dense_traffic(name):
    """The real 4-way environment at the top of the paper's traffic range: no collision, and
    vehicles keep crossing in every quarter of the run (two queues waiting for each other's
    followers once stopped all traffic)."""
    import gymnasium as gym

    import envs  # noqa: F401
    from envs.planners import make_planner
    from envs.simulation.traffic import generate_scenario

    env = gym.make("CoopIntersection4Way-v0")
    for seed in range(2):
        scenario = generate_scenario("4way", 100.0, seed, rate_range=(0.4, 0.4))
        vehicles, facts = run_episode(env, make_planner(name), scenario, 100.0, seed=seed)
        assert not facts["terminated"] and not vehicles["collided"].any()
        crossings = np.histogram(vehicles["crossed"].dropna(), bins=[0, 25, 50, 75, 100.01])[0]
        assert (crossings > 0).all(), crossings


def test_harness_runs_go_on_after_collisions():
    """The harness's environments remove crashed vehicles instead of ending the run, so a planner
    that never yields is measured over the whole duration; the user's own setting still wins."""
    from envs.evaluation import harness as evaluation
    from envs.simulation.traffic import generate_scenario

    kwargs = evaluation.evaluation_env_kwargs({"config": {"max_vehicles": 32}})
    assert kwargs["config"] == {"collision_handling": "remove", "max_vehicles": 32}
    mine = {"config": {"collision_handling": "terminate"}}
    assert evaluation.evaluation_env_kwargs(mine)["config"]["collision_handling"] == "terminate"
    with pytest.raises(ValueError, match="config"):
        evaluation.evaluation_env_kwargs({"config": [1]})

    class Reckless(PriorityRulesPlanner):
        def act(self, scene):
            return np.zeros(scene.num_vehicles)

    env = evaluation._env("CoopIntersection4Way-v0", {})
    assert env.unwrapped.config["collision_handling"] == "remove"
    scenario = generate_scenario("4way", 40.0, 0, rate_range=(0.4, 0.4))
    vehicles, facts = run_episode(env, Reckless(), scenario, 40.0, seed=0)
    assert not facts["terminated"] and facts["duration"] == pytest.approx(40.0)
    collided = vehicles[vehicles["collided"]]
    assert len(collided) >= 4  # several crashes in one run: it went on after the first
    assert collided["removed"].notna().all()  # crashed vehicles left the scene
    assert run_metrics(vehicles, facts["duration"])["collision_rate"] == len(collided) / len(vehicles)


@pytest.mark.parametrize("name", ["pr", "fifo"])
@pytest.mark.parametrize("env_id, layout", [("CoopIntersectionInD-v0", "inD"), ("CoopIntersection3Way-v0", "3way")])
def test_baselines_collision_free_on_ind_and_3way(env_id, layout, name):
    """PR and FIFO crash nowhere on a few short scenarios of the other layouts (the inD left-turn
    pockets once let a through car rear-end a left-turner; see Simulation.leaders). The default
    environment ends the episode on a collision, so a crash shows as a short, terminated run."""
    import gymnasium as gym

    import envs  # noqa: F401
    from envs.planners import make_planner
    from envs.simulation.traffic import generate_scenario

    env = gym.make(env_id)
    crossed = 0
    for seed in range(3):
        scenario = generate_scenario(layout, 40.0, seed)
        vehicles, facts = run_episode(env, make_planner(name), scenario, 40.0, seed=seed)
        assert not facts["terminated"] and not vehicles["collided"].any(), (seed, facts)
        crossed += int(vehicles["crossed"].notna().sum())
    assert crossed >= 20  # traffic did flow through the intersection


def test_every_scheduled_vehicle_counts_even_if_it_never_appeared():
    """A planner that stops everybody jams the lanes back to the spawn points: the vehicles that
    could not appear are still in the log (stopped, delayed from their scheduled time to the end),
    so both planners are measured on the same scheduled set."""
    from envs.evaluation import harness as evaluation
    from envs.simulation.traffic import demand_scenario

    class Stopper(PriorityRulesPlanner):
        def act(self, scene):
            return np.full(scene.num_vehicles, -5.0)

    env = evaluation._env("CoopIntersection4Way-v0", {})
    scenario = demand_scenario("4way", 20.0, 0, 0.4)
    scheduled = int((scenario.time <= 20.0 + 1e-9).sum())
    rows = {}
    for planner in (Stopper(), PriorityRulesPlanner()):
        vehicles, facts = run_episode(env, planner, scenario, 20.0, seed=0)
        row = run_metrics(vehicles, facts["duration"])
        rows[type(planner).__name__] = row
        assert row["vehicles"] == row["vehicles_scheduled"] == scheduled
        assert row["not_spawned"] == facts["waiting_at_end"]
        waiting = add_travel_times(vehicles[~vehicles["spawned"]])
        assert waiting["stopped"].all() and waiting["crossed"].isna().all()
        np.testing.assert_allclose(waiting["delay"], facts["duration"] - waiting["scheduled"])
        late = add_travel_times(vehicles[vehicles["crossed"].notna()])
        # delay counts the wait for a free spawn point (minus at most a few tenths from speeding in turns)
        assert (late["delay"] >= late["first_seen"] - late["scheduled"] - 0.5).all()
    stopper, pr = rows["Stopper"], rows["PriorityRulesPlanner"]
    assert stopper["not_spawned"] > pr["not_spawned"] >= 0 and stopper["crossed"] == 0
    assert stopper["stop_ratio_all"] == 1.0 and stopper["delay_mean"] > pr["delay_mean"]
