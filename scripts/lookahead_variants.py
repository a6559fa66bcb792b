"""``lookahead``'s other settings, as planner classes for ``--planner FILE:CLASS`` (docs/baselines.md). Besides
``OneWindow``, they search one window for all roads (as measured there)::

    sb3-graph evaluate --planner lookahead+shield --planner scripts/lookahead_variants.py:OneWindow+shield \\
        --planner scripts/lookahead_variants.py:StopPrice5+shield --trust-planner-files \\
        --scenarios 10 --duration 100 --seed 5000 --jobs 1
"""

from __future__ import annotations

import numpy as np

from envs.planners.glide import GlidePlanner
from envs.planners.idm import idm_acceleration
from envs.planners.lookahead import LookaheadParams, LookaheadPlanner


class OneWindow(LookaheadPlanner):
    """One window for all approach roads, without the default's greedy pass per road (about 4x cheaper)."""

    def __init__(self) -> None:
        super().__init__("LookaheadOneWindow", LookaheadParams(per_approach=False))


class StopPrice5(LookaheadPlanner):
    """A stop priced at 5 s of delay instead of 2 s."""

    def __init__(self) -> None:
        super().__init__("LookaheadStop5", LookaheadParams(stop_price=5.0, per_approach=False))


class Rollouts3Hz(LookaheadPlanner):
    """Rollouts that decide 3 times a second instead of 5 (40 % fewer planning steps per search)."""

    def __init__(self) -> None:
        super().__init__("Lookahead3Hz", LookaheadParams(rollout_frequency=3, per_approach=False))


class Hold(LookaheadPlanner):
    """Advice once given holds to the line (glide's rule for a policy's windows): a search changes only the
    vehicles not yet advised."""

    def __init__(self) -> None:
        super().__init__("LookaheadHold", LookaheadParams(hold=True, per_approach=False))


class Async(LookaheadPlanner):
    """The search beside the steps (``mode="async"``), emulated deterministically in simulated time: each search
    starts from the scene predicted one period ahead, and its windows land one period after it starts (what the
    server's search process gives when no search is late)."""

    def __init__(self) -> None:
        super().__init__("LookaheadAsync", LookaheadParams(mode="async"))


class Async3s(LookaheadPlanner):
    """``Async`` with searches that take 3 s (15 steps) to land: a slow search's cost, e.g. 100 vehicles on a busy
    machine (the server predicts a search as far ahead as the last ones took)."""

    def __init__(self) -> None:
        super().__init__("LookaheadAsync3s", LookaheadParams(mode="async", latency=3.0))


class Unbudgeted(LookaheadPlanner):
    """The search without its step budget (``step_budget=inf``): every wave whole, whatever the vehicles."""

    def __init__(self) -> None:
        super().__init__("LookaheadUnbudgeted", LookaheadParams(step_budget=float("inf")))


class AsyncUnbudgeted(LookaheadPlanner):
    """``Async`` without the step budget."""

    def __init__(self) -> None:
        super().__init__("LookaheadAsyncUnbudgeted", LookaheadParams(mode="async", step_budget=float("inf")))


class _IDMCappedGlide(GlidePlanner):
    """glide whose proposal is capped by IDM car following behind each vehicle's leader."""

    def act(self, scene):
        acc = super().act(scene)
        if scene.num_vehicles == 0:
            return acc
        leader = np.asarray(scene.leader)
        has = leader >= 0
        lead_speed = np.where(has, scene.speed[np.maximum(leader, 0)], 0.0)
        cap = idm_acceleration(scene.speed, scene.speed_limit, np.where(has, scene.gap, np.inf), lead_speed, scene.dt)
        return np.minimum(acc, np.maximum(cap, scene.a_min))


class IDMRollouts(LookaheadPlanner):
    """The default search whose rollouts cap glide's proposals by IDM car following, so that the rollouts' shield
    overrides fewer followers (fewer rounds of predictions per step); the real step plans as the default's."""

    def __init__(self) -> None:
        super().__init__("LookaheadIDMRollouts")

    def fork(self) -> GlidePlanner:
        twin = _IDMCappedGlide(self.name, self.params, self.idm, self.hold)
        twin.adopt(self)
        return twin


class WithStudent(LookaheadPlanner):
    """Expert iteration: the shipped student (an advice policy distilled from ``lookahead``) proposes one more
    candidate, its own windows per vehicle, at every search; the search keeps it where it costs least."""

    def __init__(self) -> None:
        from pathlib import Path

        import envs
        from envs.planners import make_planner

        policy = Path(envs.__file__).parent / "pretrained" / "coop_4way_lookahead" / "best_model.safetensors"
        proposer = make_planner(str(policy))
        super().__init__("LookaheadWithStudent", LookaheadParams(per_approach=False), proposer=proposer)


class Picker(LookaheadPlanner):
    """No search: the pick probe's graph-level classifier (``scripts/lookahead_pick_probe.py --save``) answers the
    search's pick, once a second, from the scene now (a student whose output is a pick, not a score per vehicle).
    ``SB3_GRAPH_PICKER`` names the classifier file (default ``runs/sel/picker_big.pt``)."""

    def __init__(self) -> None:
        import os
        from pathlib import Path

        import torch
        from torch import nn

        import envs
        from envs.planners import make_planner
        from sb3_graph.common.networks import GraphTrunk

        super().__init__("LookaheadPicker")
        saved = torch.load(os.environ.get("SB3_GRAPH_PICKER", "runs/sel/picker_big.pt"), weights_only=True)
        self.trunk = GraphTrunk(saved["in_dim"], 2, 64, (64, 64), "max", nn.ReLU, edge_dim=saved["edge_dim"])
        self.head = nn.Sequential(nn.Linear(128, 64), nn.ReLU(), nn.Linear(64, len(saved["picks"])))
        self.trunk.load_state_dict(saved["trunk"])
        self.head.load_state_dict(saved["head"])
        self.trunk.eval()
        self.head.eval()
        # the observation of the students of lookahead (their features), from the shipped one's file
        student = make_planner(str(Path(envs.__file__).parent / "pretrained" / "coop_4way_lookahead"
                                   / "best_model.safetensors"))  # fmt: skip
        self.space, self.features = student.scores.space, student.scores._observation_kwargs()
        order = sorted(range(len(self.search.windows)), key=lambda k: self.search.windows[k])
        self.pick_windows = [self.search.windows[k] for k in order]  # scores ascend as the windows do

    def _search(self, scene):
        import torch
        from torch_geometric.nn import global_max_pool, global_mean_pool

        from envs.planners.lookahead import _roads
        from envs.simulation.graph import build_graph_batch

        self.searches += 1
        g = build_graph_batch(scene, self.space, **self.features)
        with torch.inference_mode():
            h = self.trunk(g.x, g.edge_index, g.edge_type, g.edge_attr)
            batch = torch.zeros(h.shape[0], dtype=torch.long)
            pooled = torch.cat([global_mean_pool(h, batch, 1), global_max_pool(h, batch, 1)], dim=1)
            pick = int(self.head(pooled).argmax(1))
        return np.full(int(_roads(scene.layout).max()) + 1, self.pick_windows[pick])


class Chooser(LookaheadPlanner):
    """No search: the regret probe's network (``scripts/lookahead_regret_probe.py fit --save``) picks one window
    for all roads once a second, from the scene now and glide's plan of it. ``SB3_GRAPH_CHOOSER`` names its file
    (default ``runs/regret/chooser.pt``)."""

    def __init__(self) -> None:
        import os
        import sys
        from pathlib import Path

        here = str(Path(__file__).resolve().parent)
        if here not in sys.path:  # the probe's features and network, beside this file
            sys.path.insert(0, here)
        import lookahead_regret_probe as probe

        super().__init__("LookaheadChooser", LookaheadParams(windows=probe.WINDOWS, per_approach=False))
        self.probabilities = probe.load_chooser(os.environ.get("SB3_GRAPH_CHOOSER", "runs/regret/chooser.pt"))
        self.features = probe.features

    def _pick(self, scene) -> tuple[np.ndarray, float]:
        """The network's windows for all roads, and its probability of that pick."""
        from envs.planners.lookahead import _roads

        p = self.probabilities(self.features(self, scene))
        return np.full(int(_roads(scene.layout).max()) + 1, self.search.windows[int(p.argmax())]), float(p.max())

    def _search(self, scene):
        self.searches += 1
        return self._pick(scene)[0]


class ChooserOrSearch(Chooser):
    """``Chooser`` where it is confident, the search where it is not: a search runs when the network's top
    probability is below ``SB3_GRAPH_CONFIDENCE`` (default 0.8); ``searches_run`` counts them."""

    def __init__(self) -> None:
        import os

        super().__init__()
        self.name = "LookaheadChooserOrSearch"
        self.confidence = float(os.environ.get("SB3_GRAPH_CONFIDENCE", "0.8"))

    def reset(self, seed: int | None = None) -> None:
        super().reset(seed)
        self.searches_run = 0

    def stats(self) -> dict[str, float]:
        return {**super().stats(), "lookahead_searches_run": self.searches_run}

    def _search(self, scene):
        windows, confidence = self._pick(scene)
        if confidence >= self.confidence:
            self.searches += 1
            return windows
        self.searches_run += 1
        return LookaheadPlanner._search(self, scene)
