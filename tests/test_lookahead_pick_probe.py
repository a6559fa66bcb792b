"""``scripts/lookahead_pick_probe.py`` reads a labelling cache and reports held-out accuracy against the majority."""

import importlib.util
from pathlib import Path

import numpy as np

SCRIPT = Path(__file__).resolve().parents[1] / "scripts" / "lookahead_pick_probe.py"


def probe():
    spec = importlib.util.spec_from_file_location("lookahead_pick_probe", SCRIPT)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def cache_arrays(rng, steps, envs, nodes=4, edges=4):
    """A labelling cache's arrays: graphs of 3 vehicles, one pick for all of them per step."""
    edge_index = np.zeros((steps + 1, envs, 2, edges), np.int64)
    edge_index[..., 0, :2], edge_index[..., 1, :2] = [0, 1], [1, 2]
    edge_mask = np.zeros((steps + 1, envs, edges), np.float32)
    edge_mask[..., :2] = 1
    node_mask = np.zeros((steps + 1, envs, nodes), np.float32)
    node_mask[..., :3] = 1
    picks = rng.choice([-0.469, 0.0, 1.0], (steps, envs))
    return {
        "obs/x": rng.normal(size=(steps + 1, envs, nodes, 5)).astype(np.float32),
        "obs/edge_index": edge_index,
        "obs/edge_type": np.zeros((steps + 1, envs, edges), np.int64),
        "obs/edge_mask": edge_mask,
        "obs/node_mask": node_mask,
        "obs/edge_attr": np.zeros((steps + 1, envs, edges, 2), np.float32),
        "labels": np.repeat(picks[..., None], nodes, axis=2).astype(np.float32),
    }


def test_the_probe_reports_accuracy_on_a_cache(tmp_path, capsys):
    np.savez(tmp_path / "demonstrations-0.npz", **cache_arrays(np.random.default_rng(0), 10, 2))
    assert probe().main([str(tmp_path), "--steps", "2"]) == 0
    out = capsys.readouterr().out
    assert "20 labelled states with one pick for all vehicles (0 with a window per vehicle left out)" in out
    assert "held out" in out and "most frequent pick" in out


def test_the_probe_reads_the_shards_of_train_label_jobs(tmp_path, capsys):
    rng = np.random.default_rng(1)
    (tmp_path / "demonstrations-0").mkdir()
    for k in range(2):
        for i in range(3):
            np.savez(tmp_path / "demonstrations-0" / f"round-{k}-env-{i}.npz", **cache_arrays(rng, 4, 1))
    assert probe().main([str(tmp_path), "--steps", "2"]) == 0
    assert "24 labelled states with one pick for all vehicles" in capsys.readouterr().out


def test_the_probe_names_a_folder_without_one_cache(tmp_path, capsys):
    assert probe().main([str(tmp_path)]) == 2
    assert "must hold one demonstrations-*.npz or one folder of shards" in capsys.readouterr().err
