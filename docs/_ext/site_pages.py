"""Pages of the documentation site written from the code at every build, so that they cannot drift from it.

- the API reference, one page per package group (:func:`write_api_pages`): ``docs/_api/<group>.rst``;
- the environment reference's tables (:func:`write_environment_tables`): ``docs/_generated/*.md``, included by
  ``docs/env_reference.md``: the environments, the observation's arrays, the action types, the reward terms and
  every key of ``default_config()`` with its default, its allowed values and its meaning;
- the command-line reference (:func:`cli_reference`: every command's ``--help``, from its parser), the examples
  page (:func:`examples_page`: every file of ``examples/``) and the routes of each layout (:func:`routes_table`),
  included by ``docs/cli.md``, ``docs/examples.md`` and ``docs/scenarios.md``.

``docs/conf.py`` calls both when the builder starts.
"""

from __future__ import annotations

import json
import pkgutil
import re
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]

#: Packages whose modules the API reference documents, and module names it leaves out: the command
#: line (documented by ``sb3-graph COMMAND --help``) and private modules (compiled kernels).
API_PACKAGES = ("sb3_graph", "envs")
API_SKIP = ("commands", "cli")
#: ``sb3_graph``'s algorithm folders, documented on one page
ALGORITHMS = ("td3", "ddpg", "sac", "tqc", "crossq", "ppo", "a2c")
#: group -> the title of its page (a group not listed is titled by its name)
GROUP_TITLES = {
    "sb3_graph": "sb3_graph: the package, its registry, plugins and helpers",
    "sb3_graph.algorithms": "sb3_graph: the algorithms and their graph policies",
    "sb3_graph.common": "sb3_graph.common: spaces, batching, layers, networks, buffers, cloning",
    "sb3_graph.files": "sb3_graph.files: policy files and files from others",
    "sb3_graph.tuning": "sb3_graph.tuning: Optuna studies",
    "envs": "envs: the package and its entry points",
    "envs.simulation": "envs.simulation: layouts, engine, traffic, scene, graph, rewards, environments",
    "envs.planners": "envs.planners: the planners and the shield",
    "envs.evaluation": "envs.evaluation: harness, metrics, verdict, reports, sweeps",
    "envs.ind": "envs.ind: inD recordings",
    "envs.serve": "envs.serve: the edge server and its client",
}


def api_modules() -> list[str]:
    """Every public module of :data:`API_PACKAGES`, found on disk without importing it.

    :return: dotted module names, sorted
    """
    names = []
    for package in API_PACKAGES:
        names.append(package)
        for info in pkgutil.walk_packages([str(ROOT / package)], prefix=f"{package}."):
            parts = info.name.split(".")
            if any(part.startswith("_") or part in API_SKIP for part in parts[1:]):
                continue
            names.append(info.name)
    return sorted(names)


def api_group(name: str) -> str:
    """The page of one module: its package's sub-package, the algorithms together, top-level modules with their
    package (``sb3_graph.common.layers.layouts`` -> ``sb3_graph.common``, ``sb3_graph.td3.td3`` ->
    ``sb3_graph.algorithms``, ``sb3_graph.registry`` -> ``sb3_graph``).

    :param name: a dotted module name
    """
    parts = name.split(".")
    if len(parts) == 1 or not (ROOT / parts[0] / parts[1]).is_dir():
        return parts[0]
    if parts[0] == "sb3_graph" and parts[1] in ALGORITHMS:
        return "sb3_graph.algorithms"
    return f"{parts[0]}.{parts[1]}"


def _title(text: str, mark: str) -> str:
    return f"{text}\n{mark * len(text)}\n"


def api_pages() -> dict[str, str]:
    """``<group>.rst`` -> its text: a title, then a section and ``automodule`` per module of the group."""
    groups: dict[str, list[str]] = {}
    for name in api_modules():
        groups.setdefault(api_group(name), []).append(name)
    pages = {}
    for group, names in groups.items():
        if group == "sb3_graph.algorithms":  # one algorithm after another, each package before its modules
            names = sorted(names, key=lambda n: (ALGORITHMS.index(n.split(".")[1]), n))
        body = [_title(GROUP_TITLES.get(group, group), "=")]
        for name in names:
            body += [_title(f"``{name}``", "-"), f".. automodule:: {name}\n"]
        pages[f"{group}.rst"] = "\n".join(body)
    return pages


def _write_folder(folder: Path, wanted: dict[str, str], pattern: str) -> None:
    """Write ``wanted`` (file name -> text) into ``folder``, rewriting only what changed and removing stale files."""
    folder.mkdir(exist_ok=True)
    for stale in folder.glob(pattern):
        if stale.name not in wanted:
            stale.unlink()
    for file, text in wanted.items():
        path = folder / file
        if not path.exists() or path.read_text() != text:
            path.write_text(text)


def write_api_pages(srcdir: Path) -> None:
    """Write ``<srcdir>/_api/<group>.rst`` for every group of :func:`api_pages`, removing stale ones.

    :param srcdir: the documentation's source folder
    """
    _write_folder(Path(srcdir) / "_api", api_pages(), "*.rst")


# ---- the environment reference ---------------------------------------------------------------------------------


def markdown_text(rst: str) -> str:
    """One paragraph of a docstring (reStructuredText) as Markdown for a table cell: literals and roles as code,
    pipes escaped, lines joined.

    :param rst: the text
    """
    text = " ".join(line.strip() for line in rst.strip().splitlines())
    def role(match: re.Match) -> str:  # :class:`~a.b.C` -> ``C``, :func:`a.b` -> ``a.b``
        target = match.group(2)
        return f"``{target.split('.')[-1] if match.group(1) else target}``"

    text = re.sub(r":[a-z]+:`(~?)([^`]+)`", role, text)
    text = re.sub(r"``(.+?)``", r"`\1`", text)
    return text.replace("|", "\\|")


def docstring_bullets(doc: str) -> list[str]:
    """The items of a docstring's ``-`` lists, each joined into one line (continuation lines indented)."""
    items: list[str] = []
    for line in doc.splitlines():
        stripped = line.strip()
        if stripped.startswith("- "):
            items.append(stripped[2:])
        elif items and stripped and line.startswith("  ") and not stripped.startswith(("**", "-")):
            items[-1] += " " + stripped
        elif not stripped and items and items[-1] != "":
            items.append("")  # a blank line ends an item
    return [item for item in items if item]


def key_meanings(doc: str, keys) -> dict[str, str]:
    """Each key's meaning: the first docstring item that names it as ````key````, from its first mention on.

    :param doc: ``default_config``'s docstring
    :param keys: the configuration keys
    :return: key -> Markdown text (a key no item names is left out)
    """
    meanings = {}
    bullets = docstring_bullets(doc)
    for key in keys:
        for item in bullets:
            if f"``{key}``" in item:
                text = markdown_text(item).rstrip(";")
                alone = re.match(rf"`{re.escape(key)}`(?: (\[[^\]]+\]))?: (.*)$", text)  # "`key` [unit]: meaning"
                if alone:
                    text = alone.group(2) + (f" {alone.group(1)}" if alone.group(1) else "")
                elif text.startswith("rendering:"):
                    text = "a setting of highway-env's viewer (rendering only)"
                meanings[key] = text
                break
    return meanings


def _json(value) -> str:
    return f"`{json.dumps(value)}`".replace("|", "\\|")


def config_table() -> str:
    """The table of every ``default_config()`` key: default, allowed values, meaning (from its docstring)."""
    from envs.simulation.config import RULES
    from envs.simulation.env import CoopIntersectionEnv

    config = CoopIntersectionEnv.default_config()
    meanings = key_meanings(CoopIntersectionEnv.default_config.__doc__ or "", config)
    lines = ["| key | default | allowed values | meaning |", "|---|---|---|---|"]
    for key, value in config.items():
        rule = RULES.get(key)
        allowed = markdown_text(rule.allowed) if rule is not None else ""
        lines.append(f"| `{key}` | {_json(value)} | {allowed} | {meanings.get(key, '')} |")
    return "\n".join(lines) + "\n"


def environments_table() -> str:
    """The registered environments: id, layout, class and the first line of its docstring."""
    import importlib

    import envs

    lines = ["| id | layout | class | what it is |", "|---|---|---|---|"]
    for env_id, entry_point in envs.ENV_IDS.items():
        module, name = entry_point.split(":")
        cls = getattr(importlib.import_module(module), name)
        first = markdown_text((cls.__doc__ or "").strip().split("\n\n")[0])
        lines.append(f"| `{env_id}` | `{cls.LAYOUT}` | `{module}.{name}` | {first} |")
    return "\n".join(lines) + "\n"


def observation_table() -> str:
    """The observation's arrays with the default configuration: key, shape, dtype, bounds."""
    import gymnasium as gym

    import envs  # noqa: F401  (registers the environments)

    env = gym.make("CoopIntersection4Way-v0")
    space = env.observation_space
    lines = ["| key | shape | dtype | low | high |", "|---|---|---|---|---|"]
    for key, sub in space.spaces.items():
        low = getattr(sub, "low", None)
        high = getattr(sub, "high", None)
        low = "" if low is None else f"{float(low.min()):g}"
        high = "" if high is None else f"{float(high.max()):g}"
        lines.append(f"| `{key}` | `{tuple(sub.shape)}` | `{sub.dtype}` | {low} | {high} |")
    env.close()
    return "\n".join(lines) + "\n"


def action_table() -> str:
    """The action types: their score's unit per action unit and its default scale."""
    from envs.simulation.config import ACTION_TYPES, DEFAULT_ACTION_SCALES

    what = {
        "acceleration": "the vehicle's acceleration: -1 and +1 are `-max_acceleration` and `+max_acceleration` [m/s²]",
        "priority": "a shift of the vehicle's arrival key in glide's reservation order (lower goes earlier) [s]",
        "advice": "a shift of the distance from its line within which glide advises the vehicle [m]",
    }
    lines = ["| `type` | one action value per vehicle sets | scale per unit (default) |", "|---|---|---|"]
    for kind in ACTION_TYPES:
        scale = "`max_acceleration`" if kind == "acceleration" else f"{DEFAULT_ACTION_SCALES[kind]:g}"
        lines.append(f"| `\"{kind}\"` | {what.get(kind, '')} | {scale} |")
    return "\n".join(lines) + "\n"


def reward_table() -> str:
    """Every reward term with its weight in the task and paper presets and its meaning (the module's docstring)."""
    import envs.simulation.rewards as rewards

    meanings = key_meanings(rewards.__doc__ or "", rewards.REWARD_TERMS)
    lines = ["| term | `task` weight (default) | `paper` weight | meaning |", "|---|---:|---:|---|"]
    for term in rewards.TASK_TERMS + ("collision",) + rewards.PAPER_TERMS[:-1]:
        task = rewards.REWARD_PRESETS["task"].get(term, 0)
        paper = rewards.REWARD_PRESETS["paper"].get(term, 0)
        meaning = re.sub(r"^`[a-z_]+`:\s*", "", meanings.get(term, ""))
        lines.append(f"| `{term}` | {task:g} | {paper:g} | {meaning} |")
    return "\n".join(lines) + "\n"


ENVIRONMENT_TABLES = {
    "environments.md": environments_table,
    "observation.md": observation_table,
    "action_types.md": action_table,
    "reward_terms.md": reward_table,
    "default_config.md": config_table,
}


def write_environment_tables(srcdir: Path) -> None:
    """Write ``<srcdir>/_generated/<name>.md`` for every table of :data:`ENVIRONMENT_TABLES` and every page of
    :data:`REFERENCE_PAGES` (included by ``docs/env_reference.md``, ``docs/cli.md`` and ``docs/examples.md``).

    :param srcdir: the documentation's source folder
    """
    pages = {**ENVIRONMENT_TABLES, **REFERENCE_PAGES}
    _write_folder(Path(srcdir) / "_generated", {name: make() for name, make in pages.items()}, "*.md")


# ---- the command-line reference and the examples ---------------------------------------------------------------


def command_table() -> dict[str, tuple[str, str]]:
    """Every ``sb3-graph`` command of this repository: the package's own, then the intersection domain's (the table
    its entry point names), without reading the installed entry points, so that the page shows this checkout."""
    from envs.domain import COMMANDS as DOMAIN_COMMANDS
    from sb3_graph.cli import COMMANDS

    return {**COMMANDS, **{name: spec for name, spec in DOMAIN_COMMANDS.items() if name not in COMMANDS}}


def cli_reference(width: int = 100) -> str:
    """The command-line reference: the top-level help, then per command its one-line help and its parser's own
    ``--help`` text (the parsers themselves build it, as ``sb3-graph COMMAND --help`` prints it).

    :param width: the column width argparse wraps the help to
    """
    import argparse
    import os
    from unittest import mock

    from sb3_graph.cli import build_parser, command_parser

    table = command_table()
    with mock.patch.dict(os.environ, {"COLUMNS": str(width)}):
        parser = build_parser(table=table)
        parts = ["## `sb3-graph`\n", "```text", parser.format_help().rstrip(), "```\n"]
        for name, (_, help_text) in table.items():
            sub: argparse.ArgumentParser = command_parser(parser, name)
            parts += [f"## `sb3-graph {name}`\n", f"{markdown_text(help_text)}.\n", "```text"]
            parts += [sub.format_help().rstrip(), "```\n"]
    return "\n".join(parts)


def _first_paragraph(doc: str) -> str:
    return markdown_text(doc.strip().split("\n\n")[0])


def examples_page() -> str:
    """The examples page: per file of ``examples/``, its docstring (what it does and how to run it) and its code."""
    import ast

    parts = []
    for path in sorted((ROOT / "examples").glob("*.py")):
        source = path.read_text(encoding="utf-8")
        doc = ast.get_docstring(ast.parse(source)) or ""
        paragraphs = [p for p in doc.split("\n\n") if p.strip()]
        parts += [f"## `examples/{path.name}`\n", f"{_first_paragraph(doc)}\n"]
        for paragraph in paragraphs[1:]:
            lines = paragraph.splitlines()
            if paragraph.startswith("    "):  # an indented block after "::": the command that runs it
                parts += ["```bash", "\n".join(line[4:] for line in lines), "```\n"]
            else:
                text = markdown_text(paragraph)
                parts.append(f"{text[:-2].rstrip()}:\n" if text.endswith("::") else f"{text}\n")
        parts += ["```{code-block} python", ":linenos:", "", source.rstrip(), "```\n"]
    return "\n".join(parts)


def routes_table() -> str:
    """Per layout, every route a scenario file or a scene on the wire may name: its arms, maneuver, road, length
    and where it enters and leaves the intersection (from :func:`envs.simulation.layouts.build_layout`)."""
    import importlib

    import envs
    from envs.simulation.layouts import LAYOUT_NAMES, build_layout
    from envs.simulation.scene import MANEUVERS, PRIORITY_NAMES

    ids = {}
    for env_id, entry_point in envs.ENV_IDS.items():
        module, name = entry_point.split(":")
        ids.setdefault(getattr(importlib.import_module(module), name).LAYOUT, env_id)
    parts = []
    for name in LAYOUT_NAMES:
        layout = build_layout(name)
        parts += [f"### `{name}` (`{ids.get(name, '')}`)\n",
                  "| route | from | to | maneuver | road | length [m] | enters / leaves the intersection at [m] |",
                  "|---|---|---|---|---|---:|---:|"]  # fmt: skip
        for r, route in enumerate(layout.route_names):
            parts.append(
                f"| `{route}` | {layout.entry_arm[r]} | {layout.exit_arm[r]} | {MANEUVERS[layout.maneuver[r]]} | "
                f"{PRIORITY_NAMES[layout.priority[r]]} | {layout.length[r]:.2f} | "
                f"{layout.entry_arc[r]:.2f} / {layout.exit_arc[r]:.2f} |"
            )
        parts.append("")
    return "\n".join(parts)


#: the reference pages written beside the environment tables: the command line, the examples, the routes
REFERENCE_PAGES = {"cli.md": cli_reference, "examples.md": examples_page, "routes.md": routes_table}
