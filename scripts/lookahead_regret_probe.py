"""How much of ``lookahead``'s choice can a planner that decides from the scene now recover? A probe in regret.

``collect`` runs the search with one window for all roads (``OneWindow``) behind the shield on generated 4-way
scenarios, and at every search records the full cost of each of its three windows (no rollout stopped early) and
features of the scene now: per approach road, the vehicles before the line, within 30 m of it and standing, the
nearest one's distance, their mean speed, the ones farther than 30 m; and glide's plan of now (what the search's
glide would do: per road, the vehicles it would slow or stop, their planned delay, the same beyond 30 m).
``fit`` trains a small network on one file's searches to pick the window of least expected regret (the softmax
of its scores, weighted by each window's cost above the cheapest) and reports the held-out regret of its picks on
another file's, against always answering one window; ``--save`` keeps it for ``lookahead_variants.py:Chooser``,
which answers the pick once a second in place of the search. ``collect --driver NET`` lets a saved network drive
instead (the search's costs still recorded in the states it visits) and ``fit --more FILE`` adds such collections
to the training set: DAgger rounds::

    python scripts/lookahead_regret_probe.py collect --scenarios 32 --rates 0.1 0.2 0.3 0.4 0.5 0.6 \\
        --seed 30000 --out runs/regret/train.npz                      # 192 runs of 100 s, about 16 min
    python scripts/lookahead_regret_probe.py collect --scenarios 8 --seed 20000 --out runs/regret/test.npz
    python scripts/lookahead_regret_probe.py fit runs/regret/train.npz runs/regret/test.npz \\
        --save runs/regret/chooser.pt
    python scripts/lookahead_regret_probe.py collect --scenarios 16 --rates 0.1 0.2 0.3 0.4 0.5 0.6 \\
        --seed 40000 --driver runs/regret/chooser.pt --out runs/regret/dagger1.npz
    python scripts/lookahead_regret_probe.py fit runs/regret/train.npz runs/regret/test.npz \\
        --more runs/regret/dagger1.npz --save runs/regret/chooser1.pt

Regret is in the search's own unit: seconds lost against the lane limits by all vehicles over the 8 s horizon,
plus 2 s per new stop.
"""

from __future__ import annotations

import argparse
import math
import os
import sys
import time
from pathlib import Path

os.environ.setdefault("OMP_NUM_THREADS", "1")

import numpy as np  # noqa: E402

WINDOWS = (0.0, 30.0, math.inf)  # OneWindow's candidates, in this order


def features(planner, scene) -> np.ndarray:
    """``(F,)`` the scene now and glide's plan of it, per approach road of the 4-way layout and in all.

    :param planner: a glide (its memory is forked, not changed)
    :param scene: the scene now (with vehicles)
    """
    from envs.planners.lookahead import _roads

    roads = _roads(scene.layout)[scene.route]
    d, v = scene.dist_to_entry, scene.speed
    before = d > 0
    plan = planner.fork().reserve(scene)
    rows = np.arange(scene.num_vehicles)
    kind = plan.kind[plan.choice]
    delay = plan.arrival[rows, plan.choice] - plan.arrival.min(axis=1)
    delay = np.where(np.isfinite(delay), delay, 0.0)
    now, planned = [], []
    for r in range(4):
        m = (roads == r) & before
        far = m & (d > 30)
        now += [
            m.sum(),
            (m & (d < 30)).sum(),
            (m & (v < 1)).sum(),
            d[m].min() if m.any() else 200.0,
            v[m].mean() if m.any() else 0.0,
            far.sum(),
        ]
        planned += [
            (m & (kind == 1)).sum(),
            (m & (kind == 2)).sum(),
            delay[m].sum(),
            delay[m].max() if m.any() else 0.0,
            (far & (kind == 1)).sum(),
            (far & (kind == 2)).sum(),
            delay[far].sum(),
        ]
    now += [(~before & (scene.dist_to_exit > 0)).sum(), scene.num_vehicles]
    planned += [(kind == 1).sum(), (kind == 2).sum(), delay[before].sum()]
    return np.array(now + planned, float)


def _run(job: tuple[int, float, float, str | None]) -> tuple[np.ndarray, np.ndarray]:
    import gymnasium as gym

    import envs  # noqa: F401  (registers the environments)
    from envs.evaluation.harness import evaluation_env_kwargs
    from envs.planners.lookahead import LookaheadParams, LookaheadPlanner, _roads
    from envs.planners.shield import Shield
    from envs.simulation.traffic import generate_scenario

    seed, rate, duration, driver = job
    chooser = None if driver is None else load_chooser(driver)

    class Recording(LookaheadPlanner):
        def _search(self, scene):
            self.searches += 1
            n_roads = int(_roads(scene.layout).max()) + 1
            costs = [self.rollout(scene, np.full(n_roads, w)) for w in WINDOWS]
            x = features(self, scene)
            self.rows.append((x, costs))
            # the first cheapest, as the search picks; with a driver, its pick (DAgger: the states it visits)
            return np.full(n_roads, WINDOWS[int(np.argmin(costs) if chooser is None else np.argmax(chooser(x)))])

    env = gym.make("CoopIntersection4Way-v0", **evaluation_env_kwargs({}))
    scenario = generate_scenario("4way", duration, seed, rate_range=(rate, rate))
    env.reset(seed=seed, options={"scenario": scenario})
    teacher = Recording(params=LookaheadParams(windows=WINDOWS, per_approach=False))
    planner = Shield(teacher)
    planner.reset(seed)
    teacher.rows = []
    done = False
    while not done:
        acc = planner.act(env.unwrapped.scene())
        _, _, terminated, truncated, _ = env.step(env.unwrapped.accelerations_to_action(acc))
        done = terminated or truncated
    x = np.array([r[0] for r in teacher.rows]).reshape(len(teacher.rows), -1)
    return x, np.array([r[1] for r in teacher.rows]).reshape(len(teacher.rows), len(WINDOWS))


def load_chooser(path: str):
    """A network saved by ``fit --save``, as ``features -> (3,) probabilities of the windows``."""
    import torch

    saved = torch.load(path, weights_only=True)
    net = make_net(len(saved["mu"]), saved["hidden"])
    net.load_state_dict(saved["state"])
    net.eval()
    mu, sd = saved["mu"].numpy(), saved["sd"].numpy()

    def probabilities(x: np.ndarray) -> np.ndarray:
        with torch.inference_mode():
            return torch.softmax(net(torch.as_tensor((x - mu) / sd, dtype=torch.float32)[None]), 1)[0].numpy()

    return probabilities


def _fresh(path: Path | None, flag: str) -> bool:
    """``path`` may be written (it does not exist); else one line on stderr. Checked before the work, and again
    when the file is written (:func:`~sb3_graph.files.output_folders.write_file_atomically`)."""
    if path is not None and (path.exists() or path.is_symlink()):
        print(f"error: {flag}: {str(path)!r} exists; choose a new file name", file=sys.stderr)
        return False
    return True


def _regret(data) -> np.ndarray:
    """``(N, 3)`` each window's cost above the cheapest of its search."""
    return data["costs"] - data["costs"].min(1, keepdims=True)


def collect(args: argparse.Namespace) -> int:
    from multiprocessing import get_context

    from sb3_graph.files.output_folders import OutputError, write_file_atomically

    if not _fresh(args.out, "--out"):
        return 2
    jobs = [
        (args.seed + 100 * i + int(round(r * 100)), r, args.duration, None if args.driver is None else str(args.driver))
        for i in range(args.scenarios)
        for r in args.rates
    ]
    tic = time.perf_counter()
    with get_context("fork").Pool(args.jobs) as pool:
        runs = pool.map(_run, jobs, chunksize=1)
    arrays = {
        "features": np.concatenate([x for x, _ in runs]),
        "costs": np.concatenate([c for _, c in runs]),
        "run": np.concatenate([np.full(len(c), k) for k, (_, c) in enumerate(runs)]),
        "rate": np.concatenate([np.full(len(c), job[1]) for job, (_, c) in zip(jobs, runs)]),
    }

    def write(path: Path) -> None:
        with open(path, "wb") as file:  # a file object: np.savez would add ".npz" to a path's name
            np.savez(file, **arrays)

    try:
        write_file_atomically(args.out, write, flag="--out")
    except OutputError as error:
        print(f"error: {error}", file=sys.stderr)
        return 2
    print(
        f"{sum(len(c) for _, c in runs)} searches of {len(jobs)} runs in {time.perf_counter() - tic:.0f} s: {args.out}"
    )
    return 0


def make_net(inputs: int, hidden: int):
    from torch import nn

    return nn.Sequential(
        nn.Linear(inputs, hidden), nn.ReLU(), nn.Linear(hidden, hidden), nn.ReLU(), nn.Linear(hidden, len(WINDOWS))
    )


def fit(args: argparse.Namespace) -> int:
    import torch

    from sb3_graph.files.output_folders import OutputError, write_file_atomically

    if not _fresh(args.save, "--save"):
        return 2
    torch.set_num_threads(1)
    torch.manual_seed(args.seed)
    train, test = np.load(args.train), np.load(args.test)
    x, regret = train["features"], _regret(train)
    more = [np.load(f) for f in args.more]
    x_test, regret_test = test["features"], _regret(test)
    if args.fraction < 1.0:  # a share of the training runs, for a learning curve
        runs = np.random.default_rng(args.seed).permutation(np.unique(train["run"]))
        keep = np.isin(train["run"], runs[: max(1, int(round(args.fraction * len(runs))))])
        x, regret = x[keep], regret[keep]
    if more:  # DAgger rounds: the states a network drove into, labelled with the search's costs
        x = np.concatenate([x, *(m["features"] for m in more)])
        regret = np.concatenate([regret, *(_regret(m) for m in more)])
    mu, sd = x.mean(0), x.std(0) + 1e-6
    net = make_net(x.shape[1], args.hidden)
    optimizer = torch.optim.Adam(net.parameters(), lr=1e-3, weight_decay=args.weight_decay)
    xs, rs = torch.as_tensor((x - mu) / sd, dtype=torch.float32), torch.as_tensor(regret, dtype=torch.float32)
    rng = np.random.default_rng(args.seed)
    for _ in range(args.steps):
        batch = rng.integers(0, len(x), 256)
        loss = (torch.softmax(net(xs[batch]), 1) * rs[batch]).sum(1).mean()
        optimizer.zero_grad()
        loss.backward()
        optimizer.step()
    with torch.no_grad():
        picks = net(torch.as_tensor((x_test - mu) / sd, dtype=torch.float32)).argmax(1).numpy()
        fitted = net(xs).argmax(1).numpy()
    print(f"train: {len(x)} searches, regret of its picks {regret[np.arange(len(x)), fitted].mean():.3f}")
    held = regret_test[np.arange(len(x_test)), picks].mean()
    print(f"held out: {len(x_test)} searches; regret of its picks {held:.3f}, picks {np.bincount(picks, minlength=3)}")
    best = regret_test.argmin(1)
    print(
        "held out, always one window: "
        + ", ".join(
            f"{w:g} m {regret_test[:, k].mean():.3f} ({np.mean(best == k):.0%} of the search's picks)"
            for k, w in enumerate(WINDOWS)
        )
    )
    if args.save is not None:
        saved = {"state": net.state_dict(), "mu": torch.as_tensor(mu), "sd": torch.as_tensor(sd), "hidden": args.hidden}
        try:
            write_file_atomically(args.save, lambda path: torch.save(saved, path), flag="--save")
        except OutputError as error:
            print(f"error: {error}", file=sys.stderr)
            return 2
    return 0


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    sub = parser.add_subparsers(dest="command", required=True)
    c = sub.add_parser("collect", help="run the search and record its costs and the features")
    c.add_argument("--scenarios", type=int, default=8, help="scenarios per rate (default 8)")
    c.add_argument(
        "--rates",
        type=float,
        nargs="+",
        default=[0.2, 0.3, 0.4, 0.5, 0.6],
        help="veh/s per major lane (default 0.2-0.6)",
    )
    c.add_argument("--duration", type=float, default=100.0)
    c.add_argument("--seed", type=int, default=20000)
    c.add_argument("--jobs", type=int, default=2)
    c.add_argument("--out", type=Path, required=True)
    c.add_argument(
        "--driver",
        type=Path,
        default=None,
        help="a network of fit --save drives instead of the search "
        "(the costs are still recorded): the states it visits, for a DAgger round",
    )
    f = sub.add_parser("fit", help="train a picker on one collection, report its regret on another")
    f.add_argument("train", type=Path)
    f.add_argument("test", type=Path)
    f.add_argument("--steps", type=int, default=4000)
    f.add_argument("--hidden", type=int, default=64)
    f.add_argument("--weight-decay", type=float, default=1e-2)
    f.add_argument("--fraction", type=float, default=1.0, help="share of the training runs used (default all)")
    f.add_argument("--seed", type=int, default=0)
    f.add_argument("--save", type=Path, default=None)
    f.add_argument("--more", type=Path, action="append", default=[], help="another training collection (repeatable)")
    args = parser.parse_args(argv)
    return collect(args) if args.command == "collect" else fit(args)


if __name__ == "__main__":
    raise SystemExit(main())
