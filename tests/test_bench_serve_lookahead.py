"""``benchmarks/bench_serve_lookahead.py``: its closed loop holds the 100 vehicles it claims, and its turns serve
each planner every step once."""

import argparse
import importlib.util
import sys
from pathlib import Path

import pytest

_path = Path(__file__).resolve().parents[1] / "benchmarks" / "bench_serve_lookahead.py"
_spec = importlib.util.spec_from_file_location("bench_serve_lookahead", _path)
bench = importlib.util.module_from_spec(_spec)
sys.modules.setdefault("bench_serve_lookahead", bench)
_spec.loader.exec_module(bench)


@pytest.mark.parametrize("turn", [0, 1, 50, 7])
def test_turns_serve_every_step_of_both_planners_once_in_order(turn):
    order = bench._turns(23, turn)
    for i in (0, 1):
        assert [k for k, j in order if j == i] == list(range(23))
    if turn:  # whole turns: the planner changes only at a turn's end
        changes = [t for t in range(1, len(order)) if order[t][1] != order[t - 1][1]]
        assert all(order[t][0] % turn == 0 or order[t][0] == 0 for t in changes)


def test_the_long_4way_holds_100_vehicles_from_the_first_step_served(tmp_path):
    """The 4-way's own 80 m approaches hold about 55; with 200 m roads outside the junction the loop is full."""
    pytest.importorskip("sumolib")
    layout = bench.long_network(200.0, tmp_path)
    args = argparse.Namespace(vehicles=100, warmup=40.0, steps=50, rate=1.5, minor_factor=1.0, min_headway=0.5)
    env = bench.closed_loop(args, layout, 0)
    scene = env.unwrapped.scene()
    assert scene.layout.name == layout and scene.num_vehicles == 100
    assert scene.layout.entry_arc.min() == pytest.approx(200.0)
