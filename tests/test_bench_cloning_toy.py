"""``benchmarks/bench_cloning_toy.py`` gives every row of its table (cloning, RL from scratch, cloning then RL
with and without ``bc_coef``) for an off-policy and an on-policy algorithm, and counts RL's gradient steps
without the critics' warm-up of cloning."""

import sys
from pathlib import Path

BENCHMARKS = Path(__file__).resolve().parents[1] / "benchmarks"


def test_tiny_run_gives_every_row(monkeypatch, capsys):
    monkeypatch.syspath_prepend(str(BENCHMARKS))  # the script imports its neighbours by name
    import bench_cloning_toy
    import bench_toy_task

    monkeypatch.setattr(bench_cloning_toy, "error_per_vertex", lambda model: bench_toy_task.error_per_vertex(model, 2))
    argv = ["bench_cloning_toy.py", "--algos", "TD3", "PPO", "--transitions", "64", "--clone-steps", "8",
            "--rl-steps", "20", "--rl-after", "20"]  # fmt: skip
    monkeypatch.setattr(sys, "argv", argv)
    bench_cloning_toy.main()
    table = [line.split(" | ") for line in capsys.readouterr().out.splitlines() if line.startswith("| ")]
    rows = {(cells[0].strip("| "), cells[1]): cells for cells in table[2:]}
    for name, rl_steps in (("TD3", "0"), ("PPO", "20")):  # TD3: 20 steps < learning_starts; PPO: one rollout
        assert rows[name, "cloning"][3] == "8"
        assert rows[name, "RL only"][4] == rl_steps
        for coef in ("0", "0.5"):
            row = rows[name, f"cloning, then RL (bc_coef {coef})"]
            assert row[2] == "64 + 20" and row[4] == rl_steps  # the critics' 2 warm-up steps are cloning's
            assert 0.0 <= float(row[5]) < 1.0
