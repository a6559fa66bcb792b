"""scripts/drain.py replays a run with the seed the evaluation harness gave it."""

import importlib.util
from pathlib import Path

from envs.evaluation.harness import Job, run_seed

SCRIPT = Path(__file__).parents[1] / "scripts" / "drain.py"
spec = importlib.util.spec_from_file_location("drain", SCRIPT)
drain = importlib.util.module_from_spec(spec)
spec.loader.exec_module(drain)


def test_the_seed_is_the_reports_base_seed_plus_the_run(tmp_path):
    (tmp_path / "report.md").write_text("# Planner evaluation\n\n- environment: x\n- seed: 8383\n- jobs: 2\n")
    assert drain.report_seed(tmp_path) == 8383
    assert drain.report_seed(tmp_path / "missing") is None
    job = Job("pr", "PR", "scenario_002.json", 2, "CoopIntersection4Way-v0", 10.0, 8383)
    assert drain.run_seed(drain.report_seed(tmp_path), 2) == run_seed(job.seed, job.index) == 8385
