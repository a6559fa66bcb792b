"""The ``lookahead`` planner: a search by rollouts over glide's advice windows."""

from __future__ import annotations

import math

import numpy as np
import pytest
from lookahead_support import busy_scene, drive

import envs  # noqa: F401  (registers the environments)
from envs.planners import make_planner, planner_name
from envs.planners.glide import RECIPE, GlideParams, GlidePlanner
from envs.planners.lookahead import LookaheadParams, LookaheadPlanner, _rate, _simulation
from envs.planners.shield import Shield
from envs.simulation.engine import Simulation
from envs.simulation.layouts import build_layout


@pytest.mark.parametrize(
    "field, value",
    [
        ("horizon", 0.0),
        ("horizon", math.inf),
        ("windows", ()),
        ("windows", (10.0, -1.0)),
        ("windows", (float("nan"),)),
        ("period", 0),
        ("stop_price", -1.0),
        ("energy_price", float("nan")),
        ("budget", 0.0),
        ("step_budget", 0.0),
        ("per_approach", "yes"),
        ("rollout_frequency", 4),
        ("shield_horizon", 0.0),
        ("hold", 1),
    ],
)
def test_bad_lookahead_parameter_names_it_in_one_line(field, value):
    with pytest.raises(ValueError, match=f"^lookahead's {field} must be") as error:
        LookaheadParams(**{field: value})
    assert "\n" not in str(error.value)


def test_one_candidate_equal_to_glides_window_drives_as_glide_bit_for_bit():
    """With its glide's own window as its only candidate the search changes nothing: the same commands as
    that glide behind the shield at every step (and the searches ran)."""
    only = LookaheadPlanner(params=LookaheadParams(windows=(RECIPE.window,), horizon=2.0))
    assert only.params == RECIPE  # the default base of the search
    shielded = Shield(only)
    got = drive(shielded)
    want = drive(Shield(GlidePlanner(params=RECIPE)))
    assert len(got) == len(want) and all(np.array_equal(a, b) for a, b in zip(got, want))
    stats = shielded.stats()
    assert stats["lookahead_searches"] > 10 and stats["lookahead_fallbacks"] == 0
    assert stats["lookahead_rollouts"] == stats["lookahead_searches"]


def test_a_search_past_its_budget_falls_back_to_glide_and_is_counted():
    tight = LookaheadPlanner(params=LookaheadParams(budget=1e-9), glide=GlideParams())
    got = drive(Shield(tight), seconds=20.0)
    assert tight.fallbacks == tight.searches > 0
    want = drive(Shield(GlidePlanner()), seconds=20.0)
    assert all(np.array_equal(a, b) for a, b in zip(got, want))


def test_the_search_keeps_the_cheapest_candidate_and_the_greedy_pass_never_costs_more():
    scene = busy_scene()
    assert scene.num_vehicles >= 8
    params = LookaheadParams(windows=(0.0, 30.0, math.inf), horizon=4.0)
    flat = LookaheadPlanner(params=params)
    flat.reset(0)
    roads = 4
    costs = {w: flat.rollout(scene, np.full(roads, w)) for w in params.windows}
    chosen = flat._search(scene)
    assert np.all(chosen == chosen[0]) and costs[chosen[0]] == min(costs.values())
    greedy = LookaheadPlanner(params=LookaheadParams(windows=params.windows, horizon=4.0, per_approach=True))
    greedy.reset(0)
    picked = greedy._search(scene)
    assert greedy.rollout(scene, picked) <= min(costs.values())
    assert flat.rollout(scene, np.full(roads, 30.0)) == costs[30.0]  # a rollout leaves no trace


def _reference_rollout(planner: LookaheadPlanner, scene, road_windows: np.ndarray) -> float:
    """A rollout as first written (a plain simulation, the full scene every step, glide on the shield's own copy
    of it, the stopped ids looked up by id, glide planned even where no window is open): the oracle of the lean
    one."""
    from envs.planners.lookahead import _roads
    from envs.simulation.engine import Simulation
    from envs.simulation.scene import STOP_SPEED

    sim = Simulation(
        scene.layout, policy_frequency=planner.search.rollout_frequency, max_acceleration=float(scene.a_max),
        s_ref=scene.s_ref, max_vehicles=256, check_collisions=False,
    )  # fmt: skip
    sim.set_state(scene.time, scene.route, scene.vehicle_id, scene.arc, scene.speed, scene.length, scene.width)
    me = planner.fork()
    shield = Shield(me, horizon=planner.search.shield_horizon, watchdog_after=None)
    roads, stopped, lost, dt = _roads(sim.layout), planner._stopped, 0.0, sim.dt
    for _ in range(int(round(planner.search.horizon / dt))):
        if sim.num_vehicles == 0:
            break
        now = sim.scene()
        me.set_windows(road_windows[roads[now.route]])
        sim.step(shield.act(now))
        live = sim.arc - sim.length / 2 < sim.layout.exit_arc[sim.route]
        if not live.any():
            continue
        limit = np.maximum(sim.layout.limit_at(sim.route, sim.arc), 1e-3)
        lost += float(np.clip(1.0 - sim.speed[live] / limit[live], 0.0, 1.0).sum()) * dt
        new = np.setdiff1d(sim.vehicle_id[live & (sim.speed < STOP_SPEED)], stopped, assume_unique=True)
        if new.size:
            stopped = np.union1d(stopped, new)
            lost += planner.search.stop_price * new.size
    return lost


@pytest.mark.parametrize("hold", [False, True])
def test_a_lean_rollout_costs_bit_for_bit_what_the_full_one_does(hold, monkeypatch):
    """The rollouts' lean scene (shared arrays, no poses), glide without the shield's copy, stopped rows kept as
    a mask, full throttle without planning where no window is open and the compiled step cost exactly what the
    rollout as first written did; with ``hold``, advice held from before still plans glide under closed windows.
    Glide and the shield never write in the lean scene (its arrays are made read-only here)."""
    import dataclasses

    from envs.simulation.engine import Simulation

    scene = busy_scene()
    planner = LookaheadPlanner(params=LookaheadParams(hold=hold))
    planner.reset(0)
    planner._stopped = np.sort(scene.vehicle_id[np.argsort(scene.speed)[:4]])  # stopped before: not priced again
    if hold:  # advice held by the real glide: planned even where every window is closed
        planner._held = np.sort(scene.vehicle_id[scene.dist_to_entry > 0][:6])
    lean = Simulation.rollout_scene

    def read_only(sim, speed_limit=None):
        now = lean(sim, speed_limit)
        for f in dataclasses.fields(now):
            value = getattr(now, f.name)
            if isinstance(value, np.ndarray) and f.name not in ("conflicts",):
                value.flags.writeable = False
        return now

    for windows in ([0.0] * 4, [30.0] * 4, [math.inf] * 4, [0.0, 30.0, math.inf, 0.0]):
        want = _reference_rollout(planner, scene, np.array(windows))
        with monkeypatch.context() as patch:
            patch.setattr(Simulation, "rollout_scene", read_only)
            got = planner.rollout(scene, np.array(windows))
        assert got == want, windows
        assert planner.rollout(scene, np.array(windows)) == want


def test_windows_that_drive_a_road_alike_share_one_rollout_and_choose_bit_for_bit(monkeypatch):
    """A road with no vehicle before its line, or whose farthest vehicle is within two candidate windows, is driven
    alike by them: the search runs one rollout for both and still chooses as it does with a rollout each (the
    same commands at every step of a run), with fewer rollouts."""
    import envs.planners.lookahead as lookahead

    def each_its_own(scene, n_roads, windows):
        return [{w: w for w in windows} for _ in range(n_roads)]

    shared = LookaheadPlanner()
    got = drive(Shield(shared), seconds=20.0, seed=3)
    with monkeypatch.context() as patch:
        patch.setattr(lookahead, "_equivalent_windows", each_its_own)
        alone = LookaheadPlanner()
        want = drive(Shield(alone), seconds=20.0, seed=3)
    assert len(got) == len(want) and all(np.array_equal(a, b) for a, b in zip(got, want))
    assert shared.searches == alone.searches > 10
    assert shared.rollouts < alone.rollouts


def test_equivalent_windows_merge_only_what_drives_alike():
    """Every window is one on a road with no one before the line; windows at least as wide as a road's farthest
    vehicle are one; a narrower window stays its own."""
    from envs.planners.lookahead import _equivalent_windows, _roads

    scene = busy_scene()
    roads = _roads(scene.layout)[scene.route]
    windows = (0.0, 30.0, math.inf)
    same = _equivalent_windows(scene, 4, windows)
    for r in range(4):
        before = scene.dist_to_entry[(roads == r) & (scene.dist_to_entry > 0)]
        if before.size == 0:
            assert same[r] == {0.0: 0.0, 30.0: 0.0, math.inf: 0.0}
        elif before.max() < 30.0:
            assert same[r] == {0.0: 0.0, 30.0: 30.0, math.inf: 30.0}
        else:
            assert same[r] == {w: w for w in windows}


def test_a_stop_is_priced():
    """The same rollout costs more with a higher stop price exactly when a vehicle stops in it."""
    scene = busy_scene()
    free, priced = (LookaheadPlanner(params=LookaheadParams(stop_price=p, horizon=6.0)) for p in (0.0, 100.0))
    for p in (free, priced):
        p.reset(0)
    zero = np.zeros(4)  # full throttle: the shield stops vehicles at the line in this busy scene
    assert priced.rollout(scene, zero) - free.rollout(scene, zero) >= 100.0


def test_lookahead_is_a_planner_word():
    planner = make_planner("lookahead+shield")
    assert isinstance(planner.planner, LookaheadPlanner)
    assert planner_name("lookahead+shield") == "Lookahead+shield"


def test_lookahead_labels_advice_with_the_windows_it_searched():
    """The expert's score per vehicle moves glide's window to the one the search chose for the vehicle's
    approach road (the whole approach: +1), and the search plans from the environment's own scheduler."""
    from stable_baselines3.common.env_util import make_vec_env

    from envs.planners.expert import PlannerExpert
    from envs.planners.lookahead import _roads

    config = {"action": {"type": "advice"}, "shield": True, "spawn_probability_range": [0.05, 0.05]}
    vec = make_vec_env("CoopIntersection4Way-v0", n_envs=1, seed=3, env_kwargs={"config": config})
    expert = PlannerExpert("lookahead", vec)
    vec.reset()
    window, scale = GlideParams().window, 64.0
    labelled = 0
    for _ in range(15):
        scene = vec.env_method("scene")[0]
        scores = expert()
        planner = expert.planners[0]
        assert planner._held is vec.get_attr("scheduler")[0]._held  # adopted before the search
        if scene.num_vehicles:
            chosen = planner._road_windows[_roads(scene.layout)[scene.route]]
            want = np.where(np.isinf(chosen), 1.0, np.clip((chosen - window) / scale, -1.0, 1.0))
            np.testing.assert_allclose(scores[0, : scene.num_vehicles], want, rtol=0, atol=1e-6)
            labelled += 1
        vec.step(scores)
    assert expert.planners[0].searches >= 3 and labelled >= 10


def test_without_hold_a_narrower_window_releases_the_advised_vehicles():
    """With ``hold`` a vehicle advised on the whole approach keeps following its slot when the next window is
    0 m; without it (the default) every vehicle follows the window of the last search: full throttle at 0 m."""
    scene = busy_scene()
    commands = {}
    for hold in (True, False):
        planner = LookaheadPlanner(params=LookaheadParams(hold=hold, period=1e6, horizon=1.0))
        planner.reset(0)
        planner.act(scene.copy())  # the one search of the run
        planner._road_windows = np.full(4, math.inf)
        wide = planner.act(scene.copy())
        planner._road_windows = np.zeros(4)
        commands[hold] = (wide, planner.act(scene.copy()))
    wide, narrow = commands[False]
    assert np.array_equal(commands[True][0], wide) and (wide < scene.a_max).any()  # some follow a slot
    assert np.all(narrow == scene.a_max)  # released
    assert np.array_equal(commands[True][1], wide)  # held


class _Scores:
    """A scoring planner with fixed scores (in units of ``a_max``)."""

    name = "scores"

    def __init__(self, score: float) -> None:
        self.score = score

    def reset(self, seed=None) -> None:
        pass

    def act(self, scene):
        return np.full(scene.num_vehicles, self.score * scene.a_max)


def test_a_proposer_must_be_an_advice_policy():
    from envs.planners.priority import PriorityPlanner

    order = PriorityPlanner(GlidePlanner(params=RECIPE), _Scores(0.0), 5.0, kind="priority")
    with pytest.raises(ValueError, match="^lookahead's proposer must be an 'advice' policy") as error:
        LookaheadPlanner(proposer=order)
    assert "\n" not in str(error.value)


def test_a_proposal_per_vehicle_costs_as_the_same_windows_per_road_and_wins_only_when_cheaper():
    """A proposer whose windows equal a candidate's costs exactly that candidate's rollout, so it never
    displaces it (a tie keeps the candidate); the search keeps a proposal only where it costs less."""
    from envs.planners.priority import PriorityPlanner

    scene = busy_scene()
    params = LookaheadParams(windows=(0.0, 30.0), horizon=4.0)
    same = LookaheadPlanner(params=params, proposer=PriorityPlanner(GlidePlanner(params=RECIPE), _Scores(0.0), 64.0,
                                                                   kind="advice"))  # fmt: skip
    same.reset(0)
    ids = np.sort(scene.vehicle_id)
    assert same.rollout(scene, None, proposed=(ids, np.full(ids.size, 30.0))) == same.rollout(scene, np.full(4, 30.0))
    np.testing.assert_array_equal(same.propose(scene), np.full(scene.num_vehicles, 30.0))
    chosen = same._search(scene)
    assert not isinstance(chosen, tuple) and same.proposals_kept == 0
    whole = LookaheadPlanner(params=params, proposer=PriorityPlanner(GlidePlanner(params=RECIPE), _Scores(1.0), 64.0,
                                                                    kind="advice"))  # fmt: skip
    whole.reset(0)
    plain = {w: whole.rollout(scene, np.full(4, w)) for w in params.windows}
    proposal = whole.rollout(scene, None, proposed=(ids, np.full(ids.size, 94.0)))
    chosen = whole._search(scene)
    assert isinstance(chosen, tuple) == (proposal < min(plain.values()))
    assert whole.proposals_kept == int(isinstance(chosen, tuple))


def test_the_shipped_student_proposes_to_the_search():
    """``WithStudent`` (scripts/lookahead_variants.py) loads the shipped student as its proposer: an advice
    policy over glide's recipe, whose windows for a busy scene are one per vehicle, >= 0."""
    from pathlib import Path

    from envs.planners.priority import PriorityPlanner

    script = Path(__file__).resolve().parents[1] / "scripts" / "lookahead_variants.py"
    planner = make_planner(f"{script}:WithStudent")
    assert isinstance(planner, LookaheadPlanner) and isinstance(planner.proposer, PriorityPlanner)
    assert planner.proposer.kind == "advice" and planner.proposer.scheduler.params == RECIPE
    scene = busy_scene()
    planner.reset(0)
    windows = planner.propose(scene)
    assert windows.shape == (scene.num_vehicles,) and np.all(windows >= 0)


def test_the_picker_answers_one_of_the_search_windows_for_every_road(tmp_path, monkeypatch):
    """``Picker`` (scripts/lookahead_variants.py): a classifier saved by the pick probe answers the search's pick,
    one of its windows, the same for every approach road."""
    from pathlib import Path

    import torch
    from torch import nn

    from sb3_graph.common.networks import GraphTrunk

    trunk = GraphTrunk(11, 2, 64, (64, 64), "max", nn.ReLU, edge_dim=2)
    head = nn.Sequential(nn.Linear(128, 64), nn.ReLU(), nn.Linear(64, 3))
    saved = tmp_path / "picker.pt"
    torch.save({"trunk": trunk.state_dict(), "head": head.state_dict(), "picks": [-0.469, 0.0, 1.0], "in_dim": 11,
                "edge_dim": 2}, saved)  # fmt: skip
    monkeypatch.setenv("SB3_GRAPH_PICKER", str(saved))
    script = Path(__file__).resolve().parents[1] / "scripts" / "lookahead_variants.py"
    planner = make_planner(f"{script}:Picker")
    planner.reset(0)
    scene = busy_scene()
    windows = planner._search(scene)
    assert windows.shape == (4,) and len(set(windows.tolist())) == 1 and windows[0] in planner.search.windows
    assert planner.act(scene).shape == (scene.num_vehicles,)


def test_the_regret_probe_records_the_search_costs_and_its_chooser_answers_a_window(tmp_path, monkeypatch):
    """``scripts/lookahead_regret_probe.py``: ``collect`` records the three windows' costs and the features at every
    search (each cost as a fresh rollout of the search gives it), driven by the search or by a saved network;
    ``fit --save`` keeps a network that ``lookahead_variants.py:Chooser`` answers with, one window for all roads;
    an existing output of either is refused and kept."""
    from pathlib import Path

    scripts = Path(__file__).resolve().parents[1] / "scripts"
    monkeypatch.syspath_prepend(str(scripts))
    import lookahead_regret_probe as probe

    out = tmp_path / "runs.npz"
    args = ["collect", "--scenarios", "1", "--rates", "0.4", "--duration", "12", "--jobs", "1", "--seed", "3"]
    assert probe.main([*args, "--out", str(out)]) == 0
    data = np.load(out)
    assert data["costs"].shape == (len(data["features"]), 3) and len(data["costs"]) >= 10
    assert np.all(data["costs"] >= 0) and np.isfinite(data["features"]).all()
    assert probe.main([*args, "--out", str(out)]) == 2
    saved = tmp_path / "chooser.pt"
    assert probe.main(["fit", str(out), str(out), "--steps", "20", "--save", str(saved)]) == 0
    kept = saved.read_bytes()
    assert probe.main(["fit", str(out), str(out), "--steps", "20", "--save", str(saved)]) == 2  # never overwritten
    assert saved.read_bytes() == kept
    # a DAgger round: the network drives, the search's costs are recorded in the states it visits
    driven = tmp_path / "driven.npz"
    assert probe.main([*args, "--driver", str(saved), "--out", str(driven)]) == 0
    assert np.load(driven)["costs"].shape[1] == 3
    assert probe.main(["fit", str(out), str(out), "--more", str(driven), "--steps", "20"]) == 0
    monkeypatch.setenv("SB3_GRAPH_CHOOSER", str(saved))
    planner = make_planner(f"{scripts / 'lookahead_variants.py'}:Chooser")
    planner.reset(0)
    scene = busy_scene()
    windows = planner._search(scene)
    assert windows.shape == (4,) and len(set(windows.tolist())) == 1 and windows[0] in probe.WINDOWS
    assert planner.act(scene).shape == (scene.num_vehicles,)
    teacher = LookaheadPlanner(params=LookaheadParams(windows=probe.WINDOWS, per_approach=False))
    teacher.reset(0)
    assert probe.features(teacher, scene).shape == (data["features"].shape[1],)
    # ChooserOrSearch: the search where the network is less sure than the threshold, the network elsewhere
    for confidence, searched in (("1.01", 1), ("0", 0)):
        monkeypatch.setenv("SB3_GRAPH_CONFIDENCE", confidence)
        mixed = make_planner(f"{scripts / 'lookahead_variants.py'}:ChooserOrSearch")
        mixed.reset(0)
        got = mixed._search(scene)
        assert mixed.searches_run == searched and mixed.searches == 1
        assert np.array_equal(got, teacher._search(scene) if searched else windows)
        teacher.reset(0)


def test_the_rollouts_integrate_at_the_plants_rate():
    """Rollouts drive as the real step does: at the plant's rate (SUMO's 20 Hz) where the rollouts' decisions divide
    it, else at our plant's 15 Hz."""
    lay = build_layout("4way")
    for frequency, rollout, expected in ((20, 5, 20), (20, 3, 15), (15, 5, 15), (30, 5, 30)):
        sim = Simulation(lay, simulation_frequency=frequency)
        sim.add(np.array([0]), np.array([8.0]), np.array([1]))
        scene = sim.scene()
        assert _rate(scene, rollout) == expected
        assert _simulation(scene, rollout).simulation_frequency == expected


def test_a_search_past_its_step_budget_runs_the_flat_windows_then_the_most_promising_road():
    """A step budget that holds the flat windows and one road's wave: that road is the one with the most vehicles
    before their line, the other roads keep the flat choice, and the cut is counted; without a budget the whole
    greedy pass runs."""
    from envs.planners.lookahead import _equivalent_windows, _roads

    scene = busy_scene()
    n, horizon = scene.num_vehicles, 4.0
    per_round = int(horizon * 5) * n  # rollout steps of a round x vehicles
    whole = LookaheadPlanner(params=LookaheadParams(horizon=horizon, step_budget=math.inf))
    whole.reset(0)
    whole._search(scene)
    assert whole.shrunk == 0
    cut = LookaheadPlanner(params=LookaheadParams(horizon=horizon, step_budget=per_round * 5.5))  # 3 + 2 rounds
    cut.reset(0)
    chosen = cut._search(scene)
    assert cut.shrunk == 1 and cut.rollouts <= 5 < whole.rollouts
    same = _equivalent_windows(scene, 4, cut.search.windows)
    flat = {w: cut.rollout(scene, np.full(4, w)) for w in cut.search.windows}
    best = min(cut.search.windows, key=lambda w: (flat[w], cut.search.windows.index(w)))
    before = np.bincount(_roads(scene.layout)[scene.route][scene.dist_to_entry > 0], minlength=4)
    open_roads = [r for r in range(4) if len(set(same[r].values())) > 1]
    first = max(open_roads, key=lambda r: (before[r], -r))
    assert all(chosen[r] == best for r in range(4) if r != first)
    assert cut.rollout(scene, chosen) <= flat[best]
    single = LookaheadPlanner(params=LookaheadParams(horizon=horizon, step_budget=per_round * 1.5))
    single.reset(0)
    assert np.all(single._search(scene) == 0.0) and single.rollouts == 0 and single.shrunk == 1  # the first flat
