"""The results tables of README.md and docs/results.md, from one summary file.

The main job's figures live in ``docs/results/main.json``: the small part of an ``sb3-graph evaluate``
report (``summary.json``, ``paired.csv``, ``run.json``) that the tables show. This script writes the
tables between marker comments (``<!-- results:NAME -->`` ... ``<!-- /results:NAME -->``) of both pages,
so that the README and the results page cannot disagree.

After a new main job (``sb3-graph evaluate --scenarios 100 --jobs 2 --out reports/main100``)::

    python scripts/results_tables.py --report reports/main100

reads the report into ``docs/results/main.json`` (and its figures into ``docs/figures/main/``) and rewrites
both pages; without ``--report`` it
rewrites them from the committed file, and ``--check`` only says whether they are up to date (exit
status 1 when not; ``tests/test_results_tables.py`` runs it).
"""

from __future__ import annotations

import argparse
import json
import math
import re
import sys
import time
from collections.abc import Mapping
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))  # the checkout's envs, installed or not
from envs.evaluation.comparison import PAIRED_COLUMNS, PAIRED_DISPLAY  # noqa: E402

DATA = ROOT / "docs" / "results" / "main.json"
#: page -> the tables it holds
PAGES = {
    ROOT / "README.md": ("main-summary", "main-table"),
    ROOT / "docs" / "results.md": ("main-summary", "main-table", "main-groups", "main-paired", "main-figures"),
}
#: the report's figures that the results page shows, copied by --report into FIGURES_DIR
FIGURES = ("flow_rate.png", "delay_collisions.png", "stops_by_maneuver.png")
FIGURES_DIR = ROOT / "docs" / "figures" / "main"
#: report name -> how the tables name a planner (a name not listed shows as it is)
LABELS = {
    "PR": "PR (static priority rules)",
    "FIFO": "FIFO",
    "AIM": "AIM (reservations per conflict zone)",
    "SIGNAL": "SIGNAL (actuated traffic signal)",
    "FullThrottle+shield": "always full throttle + shield",
    "Glide+shield": "glide (arrival times) + shield",
    "RL:coop_4way_advice": "GNN advice policy (shipped), no shield",
    "RL:coop_4way_advice+shield": "GNN advice policy (shipped) + shield",
}
#: report name -> its short name, in the summary sentence
SHORT = {
    "FullThrottle+shield": "full throttle + shield",
    "Glide+shield": "glide + shield",
    "RL:coop_4way_advice": "the GNN advice policy without the shield",
    "RL:coop_4way_advice+shield": "the GNN advice policy + shield",
}
#: summary.json -> main.json: per planner, the figures the tables show
GROUPS = ("all", "major", "minor", "left", "straight", "right")


def _number(value: Any) -> float | None:
    """A finite float, or ``None`` (JSON's null) for a missing, empty or non-finite value."""
    if value is None or value == "":
        return None
    value = float(value)
    return value if math.isfinite(value) else None


def read_report(report: Path, command: str | None = None) -> dict[str, Any]:
    """The figures of an ``sb3-graph evaluate`` report that the tables show (the content of ``main.json``).

    :param report: the report folder (``summary.json``, ``paired.csv``, ``run.json``)
    :param command: the command that made it, as shown on the pages (default: rebuilt from ``run.json``)
    :return: ``{"source", "command", "date", "scenarios", "duration_s", "seed", "vehicles", "planners", "paired"}``
    """
    summary = json.loads((report / "summary.json").read_text())
    run = json.loads((report / "run.json").read_text()) if (report / "run.json").is_file() else {}
    replay = run.get("replay", {})
    planners = {}
    for name, s in summary.items():
        if "flow_rate" not in s:  # a planner all of whose runs failed
            continue
        planners[name] = {
            "flow_median": s["flow_rate"]["median"],
            "flow_q1": s["flow_rate"]["q1"],
            "flow_q3": s["flow_rate"]["q3"],
            "delay_mean": s["delay_s"]["mean"],
            "stops": {g: _number(s["stop_ratio"].get(g)) for g in GROUPS},
            "slow_ratio": _number(s.get("slow_ratio")),
            "hard_brakes_per_vehicle": _number(s.get("hard_brakes_per_vehicle")),
            "energy_kj_per_vehicle": _number(s.get("energy_kj_per_vehicle")),
            "collided": s.get("collided"),
            "vehicles": s["vehicles"],
            "not_spawned": s.get("not_spawned"),
            "shield_interventions": _number(s.get("shield_interventions")),
        }
    paired = []
    if (report / "paired.csv").is_file():
        import csv

        with (report / "paired.csv").open() as file:
            for row in csv.DictReader(file):
                if row["metric"] in PAIRED_DISPLAY:
                    paired.append({
                        "planner": row["planner"], "baseline": row["baseline"], "metric": row["metric"],
                        "pairs": int(row["pairs"]), "mean_difference": _number(row["mean_difference"]),
                        "ci_low": _number(row["ci_low"]), "ci_high": _number(row["ci_high"]),
                    })  # fmt: skip
    first = next(iter(summary.values()))
    runs = int(first.get("runs", 0))
    if command is None:
        command = f"sb3-graph evaluate --scenarios {runs} --seed {replay.get('seed', 0)} --out {report.as_posix()}"
    return {
        "source": report.as_posix(),
        "command": command,
        "date": time.strftime("%Y-%m-%d", time.gmtime((report / "summary.json").stat().st_mtime)),
        "scenarios": runs,
        "duration_s": replay.get("duration"),
        "seed": replay.get("seed"),
        "environment": replay.get("env"),
        "vehicles": int(first["vehicles"]),
        "planners": planners,
        "paired": paired,
    }


def _pct(value: float | None) -> str:
    return "n/a" if value is None else f"{100 * value:.1f} %"


def _collided(count: int | None, vehicles: int) -> str:
    if count is None:
        return "n/a"
    return f"{count:,}" + (f" ({100 * count / vehicles:.2g} %)" if count and count / vehicles >= 0.01 else "")


def _best(rows: Mapping[str, float | None], safe: set[str], lower: bool, digits: int) -> set[str]:
    """The planners (of ``safe``) whose value, rounded as shown, is the best of ``safe``."""
    shown = {n: round(v, digits) for n, v in rows.items() if n in safe and v is not None}
    if not shown:
        return set()
    target = min(shown.values()) if lower else max(shown.values())
    return {n for n, v in shown.items() if v == target}


def _cell(text: str, bold: bool) -> str:
    return f"**{text}**" if bold else text


def main_table(data: Mapping[str, Any]) -> list[str]:
    """The README's table: flow, delay, stops, slowed vehicles, energy and collisions per planner."""
    planners = data["planners"]
    safe = {n for n, p in planners.items() if p["collided"] == 0}
    best = {
        "flow": _best({n: p["flow_median"] for n, p in planners.items()}, safe, False, 3),
        "delay": _best({n: p["delay_mean"] for n, p in planners.items()}, safe, True, 1),
        "stops": _best({n: p["stops"]["all"] for n, p in planners.items()}, safe, True, 3),
        "minor": _best({n: p["stops"]["minor"] for n, p in planners.items()}, safe, True, 3),
        "slow": _best({n: p["slow_ratio"] for n, p in planners.items()}, safe, True, 3),
        "energy": _best({n: p["energy_kj_per_vehicle"] for n, p in planners.items()}, safe, True, 0),
    }
    lines = [
        "| planner | flow, median (q1-q3) [veh/s] | mean delay [s] | stopped, of all vehicles: all / minor road "
        "| slowed below 2 m/s | energy [kJ/veh] | collided vehicles |",
        "|---|---:|---:|---:|---:|---:|---:|",
    ]
    for name, p in planners.items():
        energy = "n/a" if p["energy_kj_per_vehicle"] is None else f"{p['energy_kj_per_vehicle']:.0f}"
        cells = [
            LABELS.get(name, name),
            _cell(f"{p['flow_median']:.3f}", name in best["flow"]) + f" ({p['flow_q1']:.3f}-{p['flow_q3']:.3f})",
            _cell(f"{p['delay_mean']:.1f}", name in best["delay"]),
            _cell(_pct(p["stops"]["all"]), name in best["stops"])
            + " / "
            + _cell(_pct(p["stops"]["minor"]), name in best["minor"]),
            _cell(_pct(p["slow_ratio"]), name in best["slow"]),
            _cell(energy, name in best["energy"]),
            _cell(_collided(p["collided"], p["vehicles"]), name in safe),
        ]
        lines.append("| " + " | ".join(cells) + " |")
    lines += ["", "Stopped and slowed: shares of all the vehicles scheduled in the runs, pooled over the scenarios. "
              "Bold: the best value of the planners none of whose vehicles collided."]
    return lines


def groups_table(data: Mapping[str, Any]) -> list[str]:
    """The results page's table of stopped vehicles per road and maneuver, jams and shield interventions."""
    lines = [
        "| planner | stopped, of all vehicles: all | major | minor | left | straight | right | not spawned (jam) "
        "| shield interventions |",
        "|---|---:|---:|---:|---:|---:|---:|---:|---:|",
    ]
    for name, p in data["planners"].items():
        stops = " | ".join(_pct(p["stops"][g]) for g in GROUPS)
        jam = "n/a" if p["not_spawned"] is None else f"{p['not_spawned']:,}"
        lines.append(f"| {LABELS.get(name, name)} | {stops} | {jam} | {_pct(p['shield_interventions'])} |")
    return lines


def paired_table(data: Mapping[str, Any]) -> list[str]:
    """The results page's table of paired differences against the report's strongest baseline."""
    rows = data["paired"]
    if not rows:
        return ["The report has no paired differences (no baseline planner ran)."]
    baseline = rows[0]["baseline"]
    metrics = [m for m in PAIRED_DISPLAY if any(r["metric"] == m for r in rows)]
    lines = [
        f"Per scenario, planner minus {LABELS.get(baseline, baseline)} (the strongest baseline): mean over the "
        f"{rows[0]['pairs']} scenarios and its 95 % bootstrap interval; pp: percentage points. Δ stops and Δ slowed "
        "are differences of each run's share of its vehicles, a mean per run (not a share of all vehicles).",
        "",
        "| planner | " + " | ".join(PAIRED_DISPLAY[m][0] for m in metrics) + " |",
        "|---|" + "---:|" * len(metrics),
    ]
    for planner in dict.fromkeys(r["planner"] for r in rows):
        cells = []
        for metric in metrics:
            found = [r for r in rows if r["planner"] == planner and r["metric"] == metric]
            if not found or None in (found[0]["mean_difference"], found[0]["ci_low"], found[0]["ci_high"]):
                cells.append("n/a")
                continue
            _, scale, digits = PAIRED_DISPLAY[metric]
            r = found[0]
            mean, low, high = (scale * r[k] for k in ("mean_difference", "ci_low", "ci_high"))
            clear = low > 0 or high < 0
            cells.append(_cell(f"{mean:+.{digits}f}", clear) + f" [{low:+.{digits}f}, {high:+.{digits}f}]")
        lines.append(f"| {LABELS.get(planner, planner)} | " + " | ".join(cells) + " |")
    lines += ["", "Bold: the interval excludes zero."]
    return lines


def summary_text(data: Mapping[str, Any]) -> list[str]:
    """What the main job is, and its verdict in one sentence (as the report's own ``In short``)."""
    import pandas as pd

    from envs.evaluation.verdict import summary_sentence

    vehicles = data["vehicles"]
    length = "" if data.get("duration_s") is None else f" of {data['duration_s']:g} s"
    where = "" if data.get("environment") is None else f" on `{data['environment']}`"
    seed = "" if data.get("seed") is None else f" (seed {data['seed']})"
    what = (
        f"`{data['command']}` ({data['date']}): every planner on the same {data['scenarios']} generated scenarios"
        f"{length}{where}{seed}, {vehicles:,} vehicles scheduled per planner."
    )
    paired = pd.DataFrame(data["paired"], columns=list(PAIRED_COLUMNS))
    named = paired.assign(planner=paired["planner"].map(lambda n: SHORT.get(n, n)))
    named["baseline"] = named["baseline"].map(lambda n: SHORT.get(n, n))
    collided = {SHORT.get(n, n): p["collided"] or 0 for n, p in data["planners"].items()}
    return [what, "", summary_sentence(named, collided=collided)]


def figures_text(data: Mapping[str, Any]) -> list[str]:
    """The report's figures copied into ``docs/figures/main/`` (none: a line that says how to get them)."""
    present = [name for name in FIGURES if (FIGURES_DIR / name).is_file()]
    if not present:
        return [f"The figures of `{data['source']}` are in its folder (`{'`, `'.join(FIGURES)}`)."]
    return [f"![{name[:-4].replace('_', ' ')}](figures/main/{name})" for name in present]


TABLES = {"main-summary": summary_text, "main-table": main_table, "main-groups": groups_table,
          "main-paired": paired_table, "main-figures": figures_text}  # fmt: skip


def render_page(text: str, data: Mapping[str, Any], names: tuple[str, ...], page: str = "page") -> str:
    """``text`` with each table of ``names`` written between its markers.

    :raises ValueError: a marker pair is missing
    """
    for name in names:
        pattern = re.compile(rf"(<!-- results:{name} -->\n).*?(<!-- /results:{name} -->)", re.DOTALL)
        if not pattern.search(text):
            raise ValueError(f"{page}: no '<!-- results:{name} -->' ... '<!-- /results:{name} -->' markers")
        body = "\n".join(TABLES[name](data))
        text = pattern.sub(lambda m, body=body: f"{m.group(1)}{body}\n{m.group(2)}", text)
    return text


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--report", type=Path, help="an evaluate report folder: read it into the summary file first")
    parser.add_argument("--command", help="the command that made --report, as the pages show it")
    parser.add_argument("--data", type=Path, default=DATA, help="the summary file (default: docs/results/main.json)")
    parser.add_argument("--check", action="store_true", help="write nothing; exit 1 when a page is out of date")
    args = parser.parse_args(argv)
    if args.report is not None:
        if not (args.report / "summary.json").is_file():
            print(f"--report: {args.report} has no summary.json (not an evaluate report)", file=sys.stderr)
            return 2
        args.data.parent.mkdir(parents=True, exist_ok=True)
        args.data.write_text(json.dumps(read_report(args.report, args.command), indent=1) + "\n")
        import shutil

        FIGURES_DIR.mkdir(parents=True, exist_ok=True)
        for name in FIGURES:
            if (args.report / name).is_file():
                shutil.copyfile(args.report / name, FIGURES_DIR / name)
    data = json.loads(args.data.read_text())
    stale = []
    for page, names in PAGES.items():
        old = page.read_text(encoding="utf-8")
        try:
            new = render_page(old, data, names, str(page.relative_to(ROOT)))
        except ValueError as error:
            print(error, file=sys.stderr)
            return 2
        if new != old:
            stale.append(str(page.relative_to(ROOT)))
            if not args.check:
                page.write_text(new, encoding="utf-8")
    if args.check:
        print("up to date" if not stale else f"out of date: {', '.join(stale)} (run python scripts/results_tables.py)")
        return 1 if stale else 0
    print(f"wrote {', '.join(stale)}" if stale else "nothing to change")
    return 0


if __name__ == "__main__":
    sys.exit(main())
