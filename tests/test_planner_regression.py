"""The planners answer recorded scenes as they did when the scenes were recorded.

``tests/data/planner_scenes.npz`` holds scenes of short evaluation runs and the answers of the
planner of each run (``scripts/record_planner_scenes.py`` regenerates it). The shield is checked
on the recorded proposals (its answer and the vehicles it overrode), AIM and the signal are
replayed scene by scene in order (they remember vehicles from step to step).
"""

from __future__ import annotations

from pathlib import Path

import gymnasium as gym
import numpy as np
import pytest

import envs  # noqa: F401  (registers the environments)
from envs.planners import AIMPlanner, SignalPlanner
from envs.planners.shield import Shield
from envs.simulation.scene import Scene

DATA = Path(__file__).parent / "data" / "planner_scenes.npz"
FIELDS = (
    "vehicle_id", "route", "s", "position", "heading", "speed", "speed_limit", "dist_to_entry",
    "dist_to_exit", "leader", "gap", "priority", "maneuver", "length", "width", "arc",
)  # fmt: skip
SHIELD_RUNS = ("pr+shield", "aim+shield", "fullthrottle+shield", "fullthrottle+shield_3way")

_LAYOUTS: dict[str, object] = {}


def _layout(env_id: str):
    if env_id not in _LAYOUTS:
        env = gym.make(env_id)
        _LAYOUTS[env_id] = env.unwrapped.layout
        env.close()
    return _LAYOUTS[env_id]


def _scenes(data, run: str):
    """Yield ``(scene, rows)`` per recorded step: the rebuilt scene and its slice of the vehicle rows."""
    lay = _layout(str(data[f"{run}/env_id"]))
    counts = data[f"{run}/count"]
    ends = np.cumsum(counts)
    fields = {name: data[f"{run}/{name}"] for name in FIELDS}
    for t, (start, end) in enumerate(zip(ends - counts, ends)):
        rows = slice(int(start), int(end))
        scene = Scene(
            time=float(data[f"{run}/time"][t]),
            dt=float(data[f"{run}/dt"]),
            route_names=lay.route_names,
            conflicts=lay.conflicts,
            a_min=float(data[f"{run}/a_min"]),
            a_max=float(data[f"{run}/a_max"]),
            s_ref=float(data[f"{run}/s_ref"]),
            layout=lay,
            **{name: value[rows] for name, value in fields.items()},
        )
        yield scene, rows


@pytest.fixture(scope="module")
def data():
    with np.load(DATA) as recorded:
        return {key: recorded[key] for key in recorded.files}


@pytest.mark.parametrize("run", SHIELD_RUNS)
def test_shield_answers_as_recorded(data, run):
    shield = Shield(AIMPlanner())  # the wrapped planner is not asked: the proposals are recorded
    proposal, action, overridden = (data[f"{run}/{key}"] for key in ("proposal", "action", "overridden"))
    for scene, rows in _scenes(data, run):
        command = shield.check(scene, proposal[rows])
        np.testing.assert_allclose(command, action[rows], rtol=0, atol=1e-9, err_msg=f"{run} t={scene.time}")
        np.testing.assert_array_equal(shield.last_overridden, overridden[rows], err_msg=f"{run} t={scene.time}")
    assert shield.interventions == int(overridden.sum())


@pytest.mark.parametrize("run, planner", [("aim", AIMPlanner), ("signal", SignalPlanner)])
def test_planner_answers_as_recorded(data, run, planner):
    planner = planner()
    planner.reset(0)
    action = data[f"{run}/action"]
    for scene, rows in _scenes(data, run):
        np.testing.assert_allclose(planner.act(scene), action[rows], rtol=0, atol=1e-9, err_msg=f"{run} t={scene.time}")


def test_gnn_predict_is_sb3_predict(data):
    """The GNN planner's direct inference answers exactly as the policy's SB3 ``predict``."""
    from envs.planners.gnn import GNNPlanner
    from envs.simulation.graph import build_observation

    path = Path(__file__).parents[1] / "envs" / "pretrained" / "coop_4way" / "best_model.safetensors"
    planner = GNNPlanner(path)
    for k, (scene, _) in enumerate(_scenes(data, "fullthrottle+shield")):
        if k % 5 or scene.num_vehicles == 0:
            continue
        obs = build_observation(scene, planner.space)
        np.testing.assert_array_equal(planner.predict(obs), planner.model.predict(obs, deterministic=True)[0])


@pytest.mark.parametrize("run", ["aim", "fullthrottle+shield", "fullthrottle+shield_3way"])
def test_aim_compiled_is_bitwise_numpy(data, run):
    """AIM's compiled candidates and reservation passes are bitwise the NumPy oracle
    (tests/aim_reference.py), scene by scene (the full-throttle run adds vehicles that drive as no
    AIM plan would)."""
    from aim_reference import REFERENCE, reference_kernels

    from envs.planners import aim

    compiled, reference = AIMPlanner(), AIMPlanner()
    checked = 0
    for scene, _ in _scenes(data, run):
        if scene.num_vehicles == 0:
            continue
        candidates, plan, action = compiled.candidates(scene), compiled.reserve(scene), compiled.act(scene)
        with reference_kernels():
            assert aim._aim_kernel is REFERENCE
            expected_candidates, expected, expected_action = (
                reference.candidates(scene), reference.reserve(scene), reference.act(scene)
            )  # fmt: skip
        for key, value in expected_candidates.items():
            np.testing.assert_array_equal(candidates[key], value, err_msg=f"{key} t={scene.time}")
        for key in ("choice", "base", "zone_enter", "zone_leave"):
            np.testing.assert_array_equal(getattr(plan, key), getattr(expected, key), err_msg=f"{key} t={scene.time}")
        np.testing.assert_array_equal(action, expected_action, err_msg=f"t={scene.time}")
        checked += 1
    assert checked > 10 and aim._aim_kernel is not REFERENCE


def test_aim_settle_kernel_on_random_inputs():
    """The kernel against ``settle_numpy`` where the recorded scenes rarely go: dense clashes, no
    clash-free candidate (fallback), ties and nan scores, pass limits reached."""
    from aim_reference import settle_numpy

    from envs.planners._aim_kernel import settle

    rng = np.random.default_rng(0)
    for trial in range(300):
        n, c, k = rng.integers(1, 9), rng.integers(1, 12), rng.integers(1, 20)
        pair = rng.random((n, n)) < 0.5
        np.fill_diagonal(pair, False)
        pi, pj = np.nonzero(pair)
        row_i, row_j = rng.integers(0, k, pi.size), rng.integers(0, k, pi.size)
        enter = np.round(rng.uniform(0, 5, (k, c)), 1)
        leave = enter + np.round(rng.uniform(0, 2, (k, c)), 1)
        arrival = np.round(rng.uniform(0, 5, (n, c)), 1)
        score = np.round(rng.uniform(0, 5, (n, c)), 1)
        score[rng.random((n, c)) < 0.05] = np.nan
        feasible = rng.random((n, c)) < 0.8
        fallback = rng.integers(0, c, n)
        follows = rng.random(n) < 0.3
        lead_row = rng.integers(0, n, n)
        args = (int(rng.integers(1, 13)), pi, pj, row_i, row_j, enter, leave, 0.04, arrival, feasible, score,
                fallback, follows, lead_row, 1.33)  # fmt: skip
        np.testing.assert_array_equal(settle(*args), settle_numpy(*args), err_msg=f"trial {trial}")


def test_gnn_scene_batch_is_the_padded_observation(data):
    """The GNN planner's batch built from the scene answers exactly as SB3's ``predict`` on the
    padded observation (first ``n`` slots), and is the batch that SB3's observation unpads to."""
    import torch

    from envs.planners.gnn import GNNPlanner
    from envs.simulation.graph import build_graph_batch, build_observation
    from sb3_graph.common.batching import padded_to_batch
    from sb3_graph.common.layers import use_compact_rows

    path = Path(__file__).parents[1] / "envs" / "pretrained" / "coop_4way" / "best_model.safetensors"
    planner = GNNPlanner(path)
    assert planner._graph_actor
    checked = 0
    for k, (scene, _) in enumerate(_scenes(data, "fullthrottle+shield")):
        if k % 3 or scene.num_vehicles == 0:
            continue
        obs = build_observation(scene, planner.space)
        expected = planner.model.predict(obs, deterministic=True)[0][: scene.num_vehicles]
        np.testing.assert_array_equal(planner.vertex_actions(scene), expected)
        # With autograd the layers take their full aggregation layout (deduplicated, sorted):
        # the inference path's forward-only layout gives the same actions, bit for bit (with the
        # fused matmul: autograd's compact relation rows agree to float rounding only).
        obs_tensor = planner.model.obs_to_tensor(obs)[0]
        previous = use_compact_rows(False)
        try:
            with_grad = planner.model.unscale_action(planner.model.actor(obs_tensor).detach().numpy())
        finally:
            use_compact_rows(previous)
        np.testing.assert_array_equal(with_grad[0, : scene.num_vehicles], expected)
        padded = padded_to_batch({key: torch.as_tensor(value) for key, value in obs.items()})
        direct = build_graph_batch(scene, planner.space)
        for name in ("x", "edge_index", "edge_type", "batch", "node_slot"):
            assert torch.equal(getattr(direct, name), getattr(padded, name)), name
        assert (direct.num_graphs, direct.max_nodes, direct.edge_attr) == (1, padded.max_nodes, None)
        checked += 1
    assert checked > 10


def test_gnn_act_many_answers_each_scene_as_act(data):
    """Scenes of runs in lockstep, answered in one batch, get the answers of one ``act`` each
    (to float tolerance: the batched matmuls run over more rows), an empty scene none."""
    from envs.planners.gnn import GNNPlanner

    path = Path(__file__).parents[1] / "envs" / "pretrained" / "coop_4way" / "best_model.safetensors"
    planner = GNNPlanner(path)
    scenes = [scene for k, (scene, _) in enumerate(_scenes(data, "fullthrottle+shield")) if k % 4 == 0]
    empty = next(scene for scene, _ in _scenes(data, "fullthrottle+shield") if scene.num_vehicles == 0)
    assert planner.act_many([]) == []
    for start in range(0, len(scenes) - 3, 4):
        group = [scenes[start], empty, *scenes[start + 1 : start + 4]]
        answers = planner.act_many(group)
        assert len(answers) == len(group)
        for scene, answer in zip(group, answers, strict=True):
            np.testing.assert_allclose(answer, planner.act(scene), rtol=1e-5, atol=1e-5)
