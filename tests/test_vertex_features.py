"""The observation's optional vertex and zone edge features (config ``vertex_features`` and
``edge_features``, issue #22): each column is what its definition says, the shield agrees on who is
committed, and a planner file trained with them acts as the model does in training."""

import json

import gymnasium as gym
import numpy as np
import pytest
import torch
import yaml

import envs  # noqa: F401  (registers the environments)
from envs.planners import make_planner
from envs.planners.adversarial import FullThrottle
from envs.planners.glide import glide_scheduler
from envs.planners.gnn import GNNPlanner
from envs.planners.shield import Shield
from envs.simulation.graph import (
    DEFAULT_S_SCALE,
    VERTEX_FEATURES,
    build_observation,
    committed,
    edges,
    node_features,
    num_node_features,
)
from sb3_graph import TD3
from sb3_graph.cli import main

torch.set_num_threads(1)

ALL_VERTEX = list(VERTEX_FEATURES)
ZONE_EDGES = ["zone_receiver", "zone_sender"]
SMALL = {"max_vehicles": 16, "max_edges": 256, "duration": 20.0, "spawn_probability": 0.07}


def _busy_scenes(steps: int = 60, seed: int = 0):
    """Scenes of an episode driven at full throttle behind the shield: vehicles before, in and past the box."""
    env = gym.make("CoopIntersection4Way-v0", config={**SMALL, "shield": True})
    env.reset(seed=seed)
    scenes = []
    for _ in range(steps):
        env.step(np.ones(env.action_space.shape, np.float32))
        scenes.append(env.unwrapped.scene())
    env.close()
    return [scene for scene in scenes if scene.num_vehicles > 1]


def test_each_vertex_column_is_its_definition():
    scenes = _busy_scenes()
    seen_committed = set()
    for scene in scenes:
        x = node_features(scene, vertex_feature_names=ALL_VERTEX)
        assert x.shape == (scene.num_vehicles, num_node_features(ALL_VERTEX)) == (scene.num_vehicles, 12)
        np.testing.assert_array_equal(x[:, :3], node_features(scene))  # the paper's [s, v, d] first
        maneuver, priority, limit, line, zone, done = x[:, 3:6], x[:, 6], x[:, 7], x[:, 8], x[:, 9], x[:, 10]
        np.testing.assert_array_equal(x[:, 11], scene.humans.astype(np.float32))  # no human drivers here: 0
        np.testing.assert_array_equal(maneuver.argmax(axis=1), scene.maneuver)
        np.testing.assert_array_equal(maneuver.sum(axis=1), 1.0)
        np.testing.assert_array_equal(priority, (scene.priority == 1).astype(np.float32))
        np.testing.assert_allclose(limit, scene.speed_limit / 10.0, rtol=1e-6)
        np.testing.assert_allclose(line, np.clip(scene.dist_to_entry * DEFAULT_S_SCALE, -1, 4), rtol=1e-6, atol=1e-7)
        assert np.all((zone >= -1) & (zone <= 4))
        # The zone lies after the stop line on every route: a body reaches it after its front passes the line.
        before_line = scene.dist_to_entry > 0
        assert np.all(zone[before_line] >= line[before_line] - 2.5 * DEFAULT_S_SCALE - 1e-6)
        seen_committed |= set(done.tolist())
    assert seen_committed == {0.0, 1.0}


def test_committed_is_the_shields_rule():
    shield = Shield(FullThrottle())
    total, both = 0, set()
    for scene in _busy_scenes(seed=3):
        plan = shield._plan(scene)
        theirs = shield.committed(plan, plan.arc, plan.speed, float(scene.a_max))
        np.testing.assert_array_equal(committed(scene), theirs)
        total += scene.num_vehicles
        both |= set(theirs.tolist())
    assert total > 200 and both == {False, True}


def test_zone_edge_features_mirror_on_reversed_edges():
    for scene in _busy_scenes(seed=1):
        edge_index, edge_type = edges(scene)
        from envs.simulation.graph import edge_features

        attr = edge_features(scene, edge_index, ZONE_EDGES)
        crossing = edge_type == 1
        if not crossing.any():
            continue
        pairs = {(int(s), int(t)): k for k, (s, t) in enumerate(edge_index.T)}
        for k in np.flatnonzero(crossing):
            s, t = edge_index[:, k]
            back = pairs[(int(t), int(s))]
            assert attr[k, 0] == attr[back, 1] and attr[k, 1] == attr[back, 0]
        assert np.all((attr >= -1) & (attr <= 4))
        # The receiver's distance is to the zone of the two routes, never before its first zone.
        zone = node_features(scene, vertex_feature_names=["zone"])[:, 3]
        receiver = edge_index[1, crossing]
        assert np.all(attr[crossing, 0] >= zone[receiver] - 1e-6)


def test_an_unknown_feature_names_the_key():
    with pytest.raises(ValueError, match="vertex_features"):
        gym.make("CoopIntersection4Way-v0", config={"vertex_features": ["route"]})
    with pytest.raises(ValueError, match="edge_features"):
        gym.make("CoopIntersection4Way-v0", config={"edge_features": ["zone"]})
    with pytest.raises(ValueError, match="unknown"):
        num_node_features(["speed"])


def test_the_env_space_and_observation_carry_the_features():
    config = {**SMALL, "vertex_features": ["committed", "maneuver"], "edge_features": ["bearing", *ZONE_EDGES]}
    env = gym.make("CoopIntersection4Way-v0", config=config)
    obs, _ = env.reset(seed=0)
    space = env.observation_space
    assert space.node_features == 7 and space.edge_features == 3 and space.contains(obs)
    scene = env.unwrapped.scene()
    expected = build_observation(
        scene, space, edge_feature_names=config["edge_features"], vertex_feature_names=config["vertex_features"]
    )
    for key in obs:
        np.testing.assert_array_equal(obs[key], expected[key])
    with pytest.raises(ValueError, match="vertex_features"):
        build_observation(scene, space, edge_feature_names=config["edge_features"])


def test_a_planner_file_with_features_acts_as_the_model(tmp_path):
    config = {**SMALL, "vertex_features": ALL_VERTEX, "edge_features": ZONE_EDGES}
    env = gym.make("CoopIntersection4Way-v0", config=config)
    model = TD3("GraphPolicy", env, learning_starts=10, policy_kwargs={"encoder_dim": 8, "conv_dims": (8,)}, seed=0)
    model.learn(30)
    model.save(tmp_path / "model.zip")
    out = tmp_path / "features.safetensors"
    names = json.dumps({"vertex_features": ALL_VERTEX, "edge_features": ZONE_EDGES})
    assert main(["export", str(tmp_path / "model.zip"), str(out), "--planner-config", names]) == 0
    planner = make_planner(str(out))
    assert isinstance(planner, GNNPlanner) and planner.vertex_features == tuple(ALL_VERTEX)
    obs, _ = env.reset(seed=4)
    for _ in range(15):
        obs, *_ = env.step(np.ones(env.action_space.shape, np.float32))
    scene = env.unwrapped.scene()
    want = model.predict(obs, deterministic=True)[0][: scene.num_vehicles] * scene.a_max
    np.testing.assert_allclose(planner.act(scene), np.clip(want, scene.a_min, scene.a_max), atol=1e-5)
    np.testing.assert_allclose(planner.act_many([scene, scene])[1], planner.act(scene), atol=1e-5)
    # Without the names the file is refused, with a message that says how to export it.
    plain = tmp_path / "plain.safetensors"
    assert main(["export", str(tmp_path / "model.zip"), str(plain)]) == 0
    with pytest.raises(ValueError, match="planner-config"):
        make_planner(str(plain))


def test_export_takes_the_planner_config_from_the_run_folder(tmp_path, capsys):
    action = {"type": "advice", "scale": 32.0}
    config = {**SMALL, "vertex_features": ALL_VERTEX, "edge_features": ZONE_EDGES, "action": action}
    env = gym.make("CoopIntersection4Way-v0", config=config)
    model = TD3("GraphPolicy", env, learning_starts=10, policy_kwargs={"encoder_dim": 8, "conv_dims": (8,)}, seed=0)
    model.learn(20)
    run = tmp_path / "run"
    (run / "checkpoints").mkdir(parents=True)
    model.save(run / "checkpoints" / "step_20.zip")  # a checkpoint: the run files are one folder up
    (run / "run.json").write_text(json.dumps({"algo": "td3", "env": "CoopIntersection4Way-v0", "seed": 0}))
    (run / "config.yml").write_text(yaml.safe_dump({"n_timesteps": 20, "env_kwargs": {"config": config}}))
    out = tmp_path / "advice.safetensors"
    assert main(["export", str(run / "checkpoints" / "step_20.zip"), str(out)]) == 0
    assert "planner config from" in capsys.readouterr().out
    planner = make_planner(str(out))  # the scores drive glide's advice windows
    assert planner.kind == "advice" and planner.scale == 32.0 and planner.scheduler.params.control == "first_phase"
    scores = planner.scores
    assert scores.vertex_features == tuple(ALL_VERTEX) and scores.edge_features == tuple(ZONE_EDGES)
    # glide's version of the day of the export is pinned in the file
    assert scores.planner_config["action"] == {"type": "advice", "scale": 32.0, "glide": "first_phase", "hold": True}
    # --planner-config replaces the run's
    given = tmp_path / "given.safetensors"
    names = json.dumps({"vertex_features": ALL_VERTEX, "edge_features": ZONE_EDGES})
    assert main(["export", str(run / "checkpoints" / "step_20.zip"), str(given), "--planner-config", names]) == 0
    assert make_planner(str(given)).planner_config.get("action") is None
    # --planner-extra adds a key the run's environment does not hold (the critic gate) to the run's config
    gated = tmp_path / "gated.safetensors"
    assert main(["export", str(run / "checkpoints" / "step_20.zip"), str(gated), "--planner-extra",
                 '{"critic_gate": 0.2}']) == 0  # fmt: skip
    assert "--planner-extra" in capsys.readouterr().out
    loaded = make_planner(str(gated))
    assert loaded.kind == "advice" and loaded.scale == 32.0 and loaded.critic_gate == 0.2
    assert loaded.scores.vertex_features == tuple(ALL_VERTEX)
    for text in ("[1]", "{bad"):
        wrong = tmp_path / "wrong.safetensors"
        with pytest.raises(SystemExit) as exit:
            main(["export", str(run / "checkpoints" / "step_20.zip"), str(wrong), "--planner-extra", text])
        assert exit.value.code == 2
        message = capsys.readouterr().err.strip()
        assert "--planner-extra" in message.splitlines()[-1] and "Traceback" not in message
        assert not wrong.exists()
    # a run config that the domain refuses: one line naming the file and the key, nothing written
    (run / "config.yml").write_text(yaml.safe_dump({"env_kwargs": {"config": {"action": {"type": "bogus"}}}}))
    bad = tmp_path / "bad.safetensors"
    assert main(["export", str(run / "checkpoints" / "step_20.zip"), str(bad)]) == 2
    message = capsys.readouterr().err.strip()
    assert "config.yml" in message and "'action'" in message and len(message.splitlines()) == 1
    assert not bad.exists()


def test_a_critic_gate_plans_with_the_scores_only_where_the_critics_value_them_above_glide(tmp_path, monkeypatch):
    action = {"type": "advice", "scale": 64.0, "glide": "first_phase"}
    config = {**SMALL, "vertex_features": ALL_VERTEX, "action": action}
    env = gym.make("CoopIntersection4Way-v0", config=config)
    model = TD3("GraphPolicy", env, learning_starts=10, policy_kwargs={"encoder_dim": 8, "conv_dims": (8,)}, seed=0)
    model.learn(30)
    model.save(tmp_path / "model.zip")

    def export(name: str, **extra) -> str:
        out = tmp_path / f"{name}.safetensors"
        header = json.dumps({"action": action, "vertex_features": ALL_VERTEX, **extra})
        assert main(["export", str(tmp_path / "model.zip"), str(out), "--planner-config", header]) == 0
        return str(out)

    plain, gated = make_planner(export("plain")), make_planner(export("gated", critic_gate=0.0))
    assert gated.critic_gate == 0.0 and plain.critic_gate is None and plain.stats() == {}
    scenes = [scene for scene in _busy_scenes() if scene.num_vehicles > 2][::10]
    glide = glide_scheduler("first_phase")  # the file's glide (the word "glide" alone is glide without the shield)
    # the gain is the twin critics' smallest value of the scores over that of the zero action
    policy = gated.scores.model
    scene = scenes[0]
    score, gain = gated.scores.critic_gain(scene)
    obs, _ = policy.obs_to_tensor(build_observation(scene, gated.scores.space, vertex_feature_names=ALL_VERTEX))
    padded = torch.zeros((1, policy.action_space.shape[0]))
    padded[0, : scene.num_vehicles] = torch.as_tensor(score, dtype=torch.float32)
    with torch.no_grad():
        want = min(q.item() for q in policy.critic(obs, padded)) - min(
            q.item() for q in policy.critic(obs, torch.zeros_like(padded))
        )
    assert gain == pytest.approx(want, abs=1e-5)
    np.testing.assert_allclose(score, plain.offsets(scene) / 64.0, atol=1e-5)
    # gain above the margin: the scores, as without a gate; at or below it: glide alone, bit for bit
    for forced, expected in ((1.0, plain), (0.0, glide)):
        monkeypatch.setattr(type(gated.scores), "critic_gain", lambda self, s, g=forced: (plain.offsets(s) / 64.0, g))
        for planner in (gated, plain, glide):
            planner.reset(0)
        for scene in scenes:
            assert np.array_equal(gated.act(scene.copy()), expected.act(scene.copy()))
        assert gated.stats() == {"gate_steps": len(scenes), "gate_open_steps": len(scenes) if forced else 0}
    # bad values: one line naming the key
    for bad in (-1.0, "0.2"):
        with pytest.raises(ValueError, match="critic_gate must be null or a number >= 0"):
            make_planner(export(f"bad{len(str(bad))}", critic_gate=bad))


def test_a_tuning_trial_sees_the_training_features():
    from envs.evaluation.tuning import trial_planner

    config = {**SMALL, "vertex_features": ["line", "zone"], "edge_features": ["zone_sender"]}
    env = gym.make("CoopIntersection4Way-v0", config=config)
    model = TD3("GraphPolicy", env, policy_kwargs={"encoder_dim": 8, "conv_dims": (8,)}, seed=0)
    obs, _ = env.reset(seed=2)
    scene = env.unwrapped.scene()
    want = np.clip(model.predict(obs, deterministic=True)[0][: scene.num_vehicles] * scene.a_max, -5, 5)
    np.testing.assert_allclose(trial_planner(model, env.unwrapped.config).act(scene), want, atol=1e-5)
    with pytest.raises(ValueError, match="vertex_features"):
        trial_planner(model, {**env.unwrapped.config, "vertex_features": []})
