"""VertexNoiseCallback: correlated exploration noise follows its vertex when vertices leave or join."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest
from stable_baselines3.common.noise import NormalActionNoise, OrnsteinUhlenbeckActionNoise, VectorizedActionNoise

from sb3_graph import TD3
from sb3_graph.callbacks import VERTEX_ORIGIN, VertexNoiseCallback


def _callback(noise, infos) -> VertexNoiseCallback:
    callback = VertexNoiseCallback()
    callback.model = SimpleNamespace(action_noise=noise)
    callback.locals = {"infos": infos}
    return callback


def _ou(state) -> OrnsteinUhlenbeckActionNoise:
    noise = OrnsteinUhlenbeckActionNoise(np.zeros(len(state)), 0.3 * np.ones(len(state)))
    noise.noise_prev = np.asarray(state, float)
    return noise


def test_each_state_moves_with_its_vertex_and_new_vertices_start_at_zero():
    # The vertex in slot 1 left, the ones in slots 2 and 3 moved up, a new vertex joined in slot 3.
    noise = _ou([1.0, 2.0, 3.0, 4.0, 9.0, 9.0])
    assert _callback(noise, [{VERTEX_ORIGIN: np.array([0, 2, 3, -1])}])._on_step()
    np.testing.assert_array_equal(noise.noise_prev, [1.0, 3.0, 4.0, 0.0, 0.0, 0.0])


def test_vectorized_noise_moves_each_environments_own_states_only():
    first, second = _ou([0.0, 0.0, 0.0]), _ou([0.0, 0.0, 0.0])
    vectorized = VectorizedActionNoise(first, 2)
    vectorized.noises = [first, second]  # the setter resets them
    first.noise_prev, second.noise_prev = np.array([1.0, 2.0, 3.0]), np.array([5.0, 6.0, 7.0])
    _callback(vectorized, [{VERTEX_ORIGIN: np.array([2, -1])}, {}])._on_step()
    np.testing.assert_array_equal(first.noise_prev, [3.0, 0.0, 0.0])
    np.testing.assert_array_equal(second.noise_prev, [5.0, 6.0, 7.0])  # no key: unchanged


def test_an_initial_state_restarts_new_vertices_and_stateless_noise_is_left_alone():
    noise = OrnsteinUhlenbeckActionNoise(np.zeros(3), np.ones(3), initial_noise=np.array([0.5, 0.5, 0.5]))
    noise.noise_prev = np.array([1.0, 2.0, 3.0])
    _callback(noise, [{VERTEX_ORIGIN: [-1, 0]}])._on_step()
    np.testing.assert_array_equal(noise.noise_prev, [0.5, 1.0, 0.5])
    normal = NormalActionNoise(np.zeros(3), np.ones(3))
    assert _callback(normal, [{VERTEX_ORIGIN: [0]}])._on_step()
    assert _callback(None, [{VERTEX_ORIGIN: [0]}])._on_step()


def test_an_origin_past_the_noises_slots_is_refused_naming_the_key():
    with pytest.raises(ValueError, match="vertex_origin"):
        _callback(_ou([1.0, 2.0]), [{VERTEX_ORIGIN: [0, 5]}])._on_step()
    with pytest.raises(ValueError, match="vertex_origin"):
        _callback(_ou([1.0, 2.0]), [{VERTEX_ORIGIN: [0, 1, -1]}])._on_step()


def test_td3_learns_with_the_callback_on_an_environment_that_reports_origins():
    import gymnasium as gym

    import envs  # noqa: F401  (registers the environments)

    config = {"max_vehicles": 12, "max_edges": 200, "duration": 10.0, "spawn_probability": 0.07, "shield": True}
    env = gym.make("CoopIntersection4Way-v0", config=config)
    noise = OrnsteinUhlenbeckActionNoise(np.zeros(12), 0.3 * np.ones(12))
    model = TD3("GraphPolicy", env, action_noise=noise, learning_starts=30, buffer_size=200, seed=0,
                policy_kwargs={"encoder_dim": 8, "conv_dims": (8,)})
    seen = []

    class Spy(VertexNoiseCallback):
        def _on_step(self) -> bool:
            seen.append(self.locals["infos"][0][VERTEX_ORIGIN].size)
            return super()._on_step()

    model.learn(40, callback=Spy())
    assert len(seen) == 40 and max(seen) > 0
