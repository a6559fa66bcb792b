"""Glide (arrival-time planning behind the shield), and the ``"priority"`` and ``"advice"`` action types
over its scheduler."""

from __future__ import annotations

import dataclasses
import json

import gymnasium as gym
import numpy as np
import pytest

import envs  # noqa: F401  (registers the environments)
from envs.evaluation.harness import evaluation_env_kwargs, planned_accelerations
from envs.planners import make_planner
from envs.planners.glide import GLIDE_VERSIONS, GUARDED, GlideParams, GlidePlanner, glide_scheduler
from envs.planners.gnn import check_planner_config
from envs.planners.shield import Shield
from envs.simulation.traffic import generate_scenario

EMPTY = {"spawn_probability": 0.0, "initial_spawn_probability": 0.0}


def empty_env(**config):
    env = gym.make("CoopIntersection4Way-v0", config={**EMPTY, **config})
    env.reset(seed=0)
    return env


def platoon_and_minor(base, to_zone: float = 30.0, gap: float = 10.0) -> tuple[int, int]:
    """Two major-road vehicles about to cross, and a minor-road vehicle due in their stream."""
    lay = base.layout
    we, sn = lay.route_id("west->east"), lay.route_id("south->north")
    half = base.config["vehicle_length"] / 2
    zw, zs = lay.zone_start[we, sn], lay.zone_start[sn, we]
    arcs = [zw - 20 - half, zw - 20 - gap - half, zs - to_zone - half]
    base.place_vehicles([we, we, sn], arc=arcs, speed=[10.0] * 3)
    return we, sn


def drive_minor(spec: str) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The minor-road vehicle's speeds and whether its body / the majors' bodies are in their shared zone."""
    env = empty_env()
    base = env.unwrapped
    we, sn = platoon_and_minor(base)
    lay, half = base.layout, base.config["vehicle_length"] / 2
    planner = make_planner(spec)
    planner.reset(0)
    speeds, minor_in, major_in = [], [], []
    for _ in range(60):
        scene = base.scene()
        minor = np.flatnonzero(scene.route == sn)
        if minor.size:
            k = minor[0]
            speeds.append(scene.speed[k])
            minor_in.append(
                scene.arc[k] + half >= lay.zone_start[sn, we] and scene.arc[k] - half <= lay.zone_end[sn, we]
            )
            majors = scene.route == we
            arc = scene.arc[majors]
            major_in.append(bool(np.any((arc + half >= lay.zone_start[we, sn]) & (arc - half <= lay.zone_end[we, sn]))))
        _, _, terminated, _, _ = env.step(base.accelerations_to_action(planner.act(scene)))
        assert not terminated, f"{spec}: collision"
    return np.array(speeds), np.array(minor_in), np.array(major_in)


def test_glide_slows_early_instead_of_stopping():
    """A minor-road vehicle due in a two-vehicle platoon's stream: full throttle behind the shield
    stops it at the line; glide slows it early, never below its floor, and it enters the zone after
    the platoon. (Behind a platoon of three the shield still stops it: glide's window is short.)"""
    floor = GlideParams().floor
    speeds, minor_in, major_in = drive_minor("glide+shield")
    assert minor_in.any()
    first = np.flatnonzero(minor_in).min()
    assert not major_in[first:].any()  # the platoon has cleared the zone when the minor vehicle enters
    assert speeds.min() >= floor - 1e-6  # never below the floor ...
    assert speeds[:first].min() < 10.0 - 3.0  # ... but it did slow down, before the zone
    ft_speeds, _, _ = drive_minor("fullthrottle+shield")
    assert ft_speeds.min() < 0.3  # full throttle raced to the line and stopped there


class _WindowPerVehicle(GlidePlanner):
    def __init__(self, windows) -> None:
        super().__init__("Windows")
        self.windows = windows

    def advice_window(self, scene):
        return self.windows(scene)


def test_a_window_per_vehicle_equal_to_glides_drives_as_glide_and_zero_as_full_throttle():
    """``advice_window`` may give one window per vehicle: glide's own window for every vehicle commands exactly
    what glide does; a zero window for every vehicle leaves no advice, so everyone gets full throttle."""
    env = empty_env()
    base = env.unwrapped
    platoon_and_minor(base)
    window = GlideParams().window
    glide, same = make_planner("glide+shield").planner, _WindowPerVehicle(lambda s: np.full(s.num_vehicles, window))
    none, forgets = GlidePlanner(), GlidePlanner()
    for planner in (glide, same, none, forgets):
        planner.reset(0)
    slowed = 0
    for _ in range(40):
        scene = base.scene()
        a = glide.act(scene.copy())
        assert np.array_equal(same.act(scene.copy()), a)
        none.set_windows(np.zeros(scene.num_vehicles))  # as the "advice" action type's -1 for everyone
        assert np.array_equal(none.act(scene.copy()), np.full(scene.num_vehicles, scene.a_max))
        forgets.set_windows(np.zeros(scene.num_vehicles))
        forgets.act(scene.copy())  # the windows hold for one act, then glide's own window again
        assert np.array_equal(forgets.act(scene.copy()), a)
        slowed += int((a < scene.a_max).sum())
        env.step(base.accelerations_to_action(a))
    assert slowed > 0  # glide did advise someone, so the comparison saw advice


def conflict_scene(base, minor_ahead: float = 4.0):
    """A west->east leader and its follower 9 m behind; a south->north vehicle due between them."""
    lay = base.layout
    we, sn = lay.route_id("west->east"), lay.route_id("south->north")
    half = base.config["vehicle_length"] / 2
    zw, zs = lay.zone_start[we, sn], lay.zone_start[sn, we]
    base.place_vehicles(
        [we, we, sn], arc=[zw - 40 - half, zw - 49 - half, zs - 44.5 + minor_ahead - half], speed=[10.0] * 3
    )
    return base.scene()


@pytest.mark.parametrize("platoon_gap, expected", [(2.5, [0, 1, 2]), (0.0, [0, 2, 1])])
def test_platoon_batching_keeps_a_follower_behind_its_leader(platoon_gap, expected):
    """With batching the follower takes its place right behind its leader in the order; without it,
    the crossing vehicle that arrives between them goes between them."""
    scene = conflict_scene(empty_env().unwrapped)
    planner = GlidePlanner(params=GlideParams(platoon_gap=platoon_gap))
    plan = planner.reserve(scene)
    assert np.argsort(plan.order).tolist() == expected


def test_priority_shift_changes_the_order_and_zero_does_not():
    scene = conflict_scene(empty_env().unwrapped)
    planner = GlidePlanner()
    own = planner.reserve(scene).order
    planner.reset()
    planner.set_priority(np.zeros(3))
    assert np.array_equal(planner.reserve(scene).order, own)
    planner.reset()
    planner.set_priority(np.array([0.0, 0.0, -10.0]))  # the crossing vehicle first
    assert np.argsort(planner.reserve(scene).order).tolist() == [2, 0, 1]
    planner.set_priority(np.array([0.0, -10.0, 0.0]))  # a follower never before its leader
    assert np.argsort(planner.reserve(scene).order)[0] == 0


@pytest.mark.parametrize("kind", ["priority", "advice"])
def test_scores_of_zero_drive_as_glide_behind_the_shield_bit_for_bit(kind):
    """A whole run of the priority (advice) environment with zero scores, and the evaluation's way of
    running glide+shield (planned_accelerations, then the float32 action) on the same scenario: every
    vehicle's position and speed equal at every step."""
    scenario = generate_scenario("4way", 40.0, 7)
    kwargs = evaluation_env_kwargs({})
    reference = gym.make("CoopIntersection4Way-v0", **kwargs)
    config = {**kwargs["config"], "action": {"type": kind}, "shield": True}
    priority = gym.make("CoopIntersection4Way-v0", config=config)
    reference.reset(seed=7, options={"scenario": scenario})
    priority.reset(seed=7, options={"scenario": scenario})
    planner = Shield(GlidePlanner())
    planner.reset(7)
    zero = np.zeros(priority.action_space.shape, np.float32)
    steps = crossed = 0
    while True:
        ref_scene, pri_scene = reference.unwrapped.scene(), priority.unwrapped.scene()
        assert np.array_equal(ref_scene.vehicle_id, pri_scene.vehicle_id)
        assert np.array_equal(ref_scene.arc, pri_scene.arc) and np.array_equal(ref_scene.speed, pri_scene.speed)
        acc = planned_accelerations(planner, ref_scene)
        _, _, _, truncated, info = reference.step(reference.unwrapped.accelerations_to_action(acc))
        _, _, _, truncated_p, info_p = priority.step(zero)
        assert truncated == truncated_p
        crossed += info["record"].crossed.size
        steps += 1
        if truncated:
            break
    assert steps == 200 and crossed > 10
    assert np.array_equal(info_p["executed_action"], zero)


@pytest.mark.parametrize(
    "action, message",
    [
        ({"type": "speed"}, "config key 'action'"),
        ({"type": "priority", "scale": 0}, "config key 'action'"),
        ({"type": "priority", "horizon": 3}, "config key 'action'"),
        ({"type": "advice", "scale": -10.0}, "config key 'action'"),
        ("priority", "config key 'action'"),
    ],
)
def test_bad_action_config_names_the_key(action, message):
    with pytest.raises(ValueError, match=message):
        gym.make("CoopIntersection4Way-v0", config={"action": action})


@pytest.mark.parametrize("kind", ["priority", "advice"])
def test_scheduler_actions_refuse_a_residual_base(kind):
    with pytest.raises(ValueError, match=f"'residual_base' must be null with action type '{kind}'"):
        gym.make("CoopIntersection4Way-v0", config={"action": {"type": kind}, "residual_base": "aim"})


def test_advice_scores_move_each_vehicles_window():
    """``"advice"``: 0 keeps glide's window, -1 takes a vehicle out of glide's advice (its window moves by the
    default scale of 64 m, never below 0 m: full throttle); the window of a vehicle is its own."""
    env = empty_env(action={"type": "advice"}, shield=False)
    base = env.unwrapped
    assert base.config["action"] == {"type": "advice", "scale": 64.0, "glide": "first_phase", "hold": True}
    assert GlideParams().window < 64.0
    scene = conflict_scene(base)  # the minor-road vehicle, within glide's window, must yield to the major-road pair
    glide, never = GlidePlanner(), GlidePlanner()
    for planner in (glide, never):
        planner.reset(0)
    assert glide.act(scene.copy())[2] < scene.a_max  # advised: it slows
    never.set_windows(np.zeros(3))
    assert np.array_equal(never.act(scene.copy()), np.full(3, scene.a_max))  # no advice: full throttle
    other = empty_env(action={"type": "advice"}, shield=False).unwrapped
    conflict_scene(other)
    scores = np.zeros(base.action_space.shape, np.float32)
    other.step(scores)  # glide's own windows: the minor-road vehicle slows
    scores[2] = -1.0  # window 0 m for the minor-road vehicle alone
    base.step(scores)
    fast, same = base.scene().speed, other.scene().speed
    assert fast[2] > same[2] and np.array_equal(fast[:2], same[:2])


@pytest.mark.parametrize(
    "field, value",
    [
        ("window", -1.0),
        ("floor", float("nan")),
        ("floor", float("inf")),
        ("platoon_gap", "2"),
        ("decel", -3.0),
        ("stop_penalty", float("nan")),
        ("follow_headway", True),
        ("control", "idm"),
    ],
)
def test_bad_glide_parameter_names_the_field(field, value):
    with pytest.raises(ValueError, match=f"^glide's {field} must be") as error:
        GlideParams(**{field: value})
    assert "\n" not in str(error.value)


def test_glide_window_may_be_infinite():
    assert GlideParams(window=float("inf")).window == float("inf")


def test_first_phase_control_has_no_car_following_and_guarded_has():
    """Behind the shield glide commands its plan's first phase alone: the gaps to the leaders do not change
    it (the shield keeps them). The guarded control (glide without the shield) caps it by IDM car following."""
    scene = conflict_scene(empty_env().unwrapped)
    close = dataclasses.replace(scene, gap=np.full_like(scene.gap, 0.5))
    for control, follows in (("first_phase", False), ("guarded", True)):
        planner = GlidePlanner(params=GlideParams(window=float("inf"), control=control))
        plan = planner.reserve(scene.copy())
        command = planner.first_phase if control == "first_phase" else planner.control
        same = np.array_equal(command(scene, plan), command(close, plan))
        assert same != follows, control


def test_glide_without_the_shield_keeps_its_guard():
    assert make_planner("glide").params == GUARDED
    assert make_planner("glide+shield").planner.params == GlideParams()
    assert GlideParams().control == "first_phase"


@pytest.mark.parametrize(
    "action, version",
    [
        ({"type": "advice", "scale": 64.0}, "guarded"),  # written before glide had versions
        ({"type": "advice", "scale": 64.0, "glide": "first_phase"}, "first_phase"),
        ({"type": "priority", "glide": "guarded"}, "guarded"),
    ],
)
def test_policy_files_run_over_the_glide_they_were_trained_over(action, version):
    config = check_planner_config({"action": action}, "policy.safetensors")
    assert config["action"]["glide"] == version
    assert glide_scheduler(version).params == GLIDE_VERSIONS[version]


def test_advice_without_hold_releases_a_vehicle_whose_window_shrinks():
    """``"hold": false``: a vehicle advised on a wide window drives at full throttle once its window is 0 m;
    with the default hold it keeps following its slot to the line. Policy files carry the key (default true)."""
    speeds = {}
    for hold in (True, False):
        base = empty_env(action={"type": "advice", "hold": hold}, shield=False).unwrapped
        assert base._scheduler.hold is hold
        conflict_scene(base)
        scores = np.zeros(base.action_space.shape, np.float32)
        base.step(scores)  # glide's own window: the minor-road vehicle is advised
        scores[2] = -1.0  # then window 0 m
        base.step(scores)
        speeds[hold] = base.scene().speed[2]
    assert speeds[False] > speeds[True]
    assert check_planner_config({"action": {"type": "advice", "hold": False}}, "p")["action"]["hold"] is False
    assert check_planner_config({"action": {"type": "advice"}}, "p")["action"]["hold"] is True
    with pytest.raises(ValueError, match="config key 'action'.*'hold': true or false"):
        gym.make("CoopIntersection4Way-v0", config={"action": {"type": "advice", "hold": "no"}})


def test_environment_builds_the_named_glide_and_refuses_an_unknown_one():
    env = empty_env(action={"type": "advice", "glide": "guarded"})
    assert env.unwrapped._scheduler.params == GUARDED
    with pytest.raises(ValueError, match="config key 'action'.*'glide': one of"):
        gym.make("CoopIntersection4Way-v0", config={"action": {"type": "advice", "glide": "v0"}})
    with pytest.raises(ValueError, match="glide version must be one of"):
        glide_scheduler("v0")


@pytest.mark.parametrize(
    "algo, kind",
    [(algo, "priority") for algo in ("td3", "ddpg", "sac", "tqc", "crossq", "ppo", "a2c")]
    + [("td3", "advice"), ("ppo", "advice")],
)
def test_every_algorithm_trains_on_scheduler_actions(algo, kind, tmp_path):
    """A short run of every registered algorithm in the priority action space (two in the advice one)
    behind the shield; the exported file's header says what its scores mean, and ``make_planner``
    runs it over glide."""
    import torch
    from test_registry import RUNS, SMALL, STEPS

    from envs.planners.priority import PriorityPlanner
    from sb3_graph.cli import main
    from sb3_graph.registry import ALGORITHMS

    torch.set_num_threads(1)
    entry = ALGORITHMS[algo]
    config = {"action": {"type": kind, "scale": 4.0}, "shield": True}
    policy_kwargs = dict(SMALL, n_quantiles=5) if algo == "tqc" else dict(SMALL)
    env = gym.make("CoopIntersection4Way-v0", config=config)
    model = entry.load_class()("GraphPolicy", env, seed=0, policy_kwargs=policy_kwargs, device="cpu", **RUNS[algo])
    before = [p.detach().clone() for p in model.policy.parameters()]
    model.learn(STEPS)
    assert any(not torch.equal(a, b) for a, b in zip(before, model.policy.parameters())), "no gradient step ran"
    model.save(tmp_path / "model.zip")
    out = tmp_path / "planner.safetensors"
    header = json.dumps({"action": {"type": kind, "scale": 4.0}})
    assert main(["export", str(tmp_path / "model.zip"), str(out), "--planner-config", header]) == 0
    planner = make_planner(f"{out}+shield")
    inner = planner.planner
    assert isinstance(inner, PriorityPlanner) and inner.scale == 4.0 and inner.kind == kind
    env.reset(seed=1)
    for _ in range(10):
        env.step(np.zeros(env.action_space.shape, np.float32))
    scene = env.unwrapped.scene()
    scores = inner.scores.act(scene) / scene.a_max
    glide = GlidePlanner()
    if kind == "priority":
        glide.set_priority(4.0 * scores)
    else:  # the window moved by the scaled score, never below 0 m (set_scores written out)
        glide.set_windows(np.maximum(glide.params.window + 4.0 * scores, 0.0))
    np.testing.assert_array_equal(inner.act(scene), glide.act(scene))
    # a critic gate reads critics of one value each; others are refused at load, in one line naming the file
    gated = tmp_path / "gated.safetensors"
    header = json.dumps({"action": {"type": kind, "scale": 4.0}, "critic_gate": 0.0})
    assert main(["export", str(tmp_path / "model.zip"), str(gated), "--planner-config", header]) == 0
    if algo in ("td3", "ddpg", "sac"):
        assert np.isfinite(make_planner(str(gated)).scores.critic_gain(scene)[1])
    else:
        with pytest.raises(ValueError, match=f"{gated}: critic_gate needs a policy file of TD3, DDPG, SAC"):
            make_planner(str(gated))


def test_advice_once_given_holds_to_the_line():
    """A vehicle within its window at one step stays advised when a later window shrinks (a policy
    that flips between advice and full throttle would brake and accelerate in turn)."""
    scene = conflict_scene(empty_env().unwrapped)
    held, fresh = GlidePlanner(), GlidePlanner()
    held.reset(0)
    held.set_windows(np.full(3, np.inf))
    first = held.act(scene.copy())
    assert first[2] < scene.a_max  # advised over the whole approach
    held.set_windows(np.zeros(3))  # "never": but the advice was given
    fresh.reset(0)
    fresh.set_windows(np.zeros(3))
    fresh.act(scene.copy())
    fresh.set_windows(np.zeros(3))
    assert np.array_equal(held.act(scene.copy()), first)
    assert np.array_equal(fresh.act(scene.copy()), np.full(3, scene.a_max))  # never advised: full throttle


def _shifted(scene, delta):
    """The scene with every perceived arc moved by ``delta`` [m] (the distances and gaps with it)."""
    delta = np.broadcast_to(delta, scene.arc.shape)
    lead = scene.leader >= 0
    ahead = np.where(lead, delta[np.maximum(scene.leader, 0)], 0.0)
    return dataclasses.replace(
        scene, arc=scene.arc + delta, s=scene.s + delta, dist_to_entry=scene.dist_to_entry - delta,
        dist_to_exit=scene.dist_to_exit - delta, gap=np.where(lead, scene.gap + ahead - delta, scene.gap),
    )  # fmt: skip


def test_hysteresis_keeps_a_metre_of_perception_error_out_of_the_plans():
    env = gym.make("CoopIntersection4Way-v0", config={"spawn_probability": 0.6})
    env.reset(seed=3)
    for _ in range(15):
        env.step(np.zeros(env.action_space.shape, np.float32))
    exact = env.unwrapped.scene()
    assert exact.num_vehicles >= 3
    glide = GlidePlanner(params=dataclasses.replace(GlideParams(), hysteresis=1.0))
    assert glide.steadied(exact) is exact  # an exact scene is planned as it is
    perceived = dataclasses.replace(exact, arc_std=np.full(exact.num_vehicles, 1.0))
    glide.act(perceived)
    jitter = np.where(np.arange(exact.num_vehicles) % 2, 0.8, -0.6)  # within the band: the plans do not move
    steady = glide.steadied(_shifted(perceived, jitter))
    np.testing.assert_allclose(steady.arc, perceived.arc)
    np.testing.assert_allclose(steady.dist_to_entry, perceived.dist_to_entry)
    np.testing.assert_allclose(steady.gap, perceived.gap)
    np.testing.assert_array_equal(glide.act(_shifted(perceived, jitter)), glide.act(perceived))
    far = glide.steadied(_shifted(perceived, 3.0))  # beyond the band: followed as far as it lies outside
    np.testing.assert_allclose(far.arc, perceived.arc + 2.0)
    plain = GlidePlanner()
    plain.act(perceived)
    assert plain.steadied(_shifted(perceived, jitter)).arc is not perceived.arc  # no band: the perceived arcs
