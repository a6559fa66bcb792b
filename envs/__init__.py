"""The cooperative intersection domain, one folder per question.

- :mod:`envs.simulation`: how the world moves and what the learner sees (layouts, engine, traffic,
  scene, graph observation, rewards, config, the environments),
- :mod:`envs.planners`: who decides the accelerations (``envs.planners.Planner``, baselines, shield),
- :mod:`envs.evaluation`: how planners are compared (harness, executors, metrics, reports, sweeps, tuning),
- :mod:`envs.ind`: real-world traffic (inD), :mod:`envs.serve`: the planner as an edge server,
  :mod:`envs.commands`: the ``sb3-graph`` commands, ``envs/pretrained/``: the shipped planners.

Importing ``envs`` registers the gymnasium environments (their modules load only on ``gym.make``)
and names the providers of what a lower floor asks of a higher one (:mod:`envs.simulation.hooks`):
:mod:`envs.planners` for the planners the environments train with, :mod:`envs.serve.client` for
planner servers. The environments:

- ``CoopIntersection4Way-v0``: the paper's synthetic four-way intersection,
- ``CoopIntersection3Way-v0``: a T junction (major road, minor road merging),
- ``CoopIntersectionInD-v0``: the inD four-way approximation (priority road, left-turn lanes).
"""

from __future__ import annotations

from gymnasium.envs.registration import register, registry

from envs.simulation import hooks

ENV_IDS = {
    "CoopIntersection4Way-v0": "envs.simulation.env:CoopIntersection4WayEnv",
    "CoopIntersection3Way-v0": "envs.simulation.env:CoopIntersection3WayEnv",
    "CoopIntersectionInD-v0": "envs.simulation.env:CoopIntersectionInDEnv",
}

for _env_id, _entry_point in ENV_IDS.items():
    if _env_id not in registry:
        register(id=_env_id, entry_point=_entry_point)

# What a floor asks from the floors above (envs.simulation.hooks), imported on the first request: the
# planners the environments train with (shield, residual base, priority scheduler) from envs.planners,
# the client of a planner server (planner words http://HOST:PORT) from envs.serve.client.
hooks.add_provider("envs.planners")
hooks.add_provider("envs.serve.client")
