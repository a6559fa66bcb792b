"""Every ``sb3-graph`` command of README.md and docs/ parses with the real parser, as a shell would hand it over.

A command is found in a fenced block that is not Python, JSON or a directive (each line, ``\\`` continuations joined,
``#`` comments dropped, ``;``, ``&&`` and ``|`` separating commands), or in an inline code span that holds a whole
command (``sb3-graph`` and at least one word after the command name). ``python -m sb3_graph.cli`` counts as
``sb3-graph``. Before parsing, the words go through what a shell does to them: ``NAME=value`` assignments earlier in
the block (or the span) and a ``for NAME in`` loop's first value are substituted for ``$NAME``, unquoted braces are
expanded (``{a,b}``, ``{1..3}``), and quotes are removed. A command with an elision (``...``) is a sketch, not a
command, and is left out. Nothing runs: the words go to :func:`sb3_graph.cli.build_parser`'s parser, which must
accept them as ``sb3-graph`` itself would, and hold no placeholder for the reader to fill in (``ENV``, ``FILE``,
``<layout>``).
"""

from __future__ import annotations

import contextlib
import io
import re
import shlex
import sys
from pathlib import Path

import pytest

from sb3_graph.cli import build_parser

ROOT = Path(__file__).resolve().parents[1]
#: fence languages whose lines are not shell
NOT_SHELL = ("python", "json", "yaml", "{")
_FENCE = re.compile(r"^```([^\n]*)\n(.*?)^```[ \t]*$", re.DOTALL | re.MULTILINE)
_SPAN = re.compile(r"(?<!`)`([^`]+)`(?!`)")
_ASSIGNMENT = re.compile(r"^[A-Za-z_][A-Za-z0-9_]*=")
_VARIABLE = re.compile(r"\$\{?([A-Za-z_][A-Za-z0-9_]*)\}?")


def markdown_files() -> list[Path]:
    """README.md and every Markdown page of docs/, generated folders left out."""
    pages = sorted(p for p in (ROOT / "docs").rglob("*.md") if not {"_build", "_api", "_generated"} & set(p.parts))
    return [ROOT / "README.md", *pages]


def expand_braces(word: str) -> list[str]:
    """Bash's brace expansion of one unquoted word: ``a{b,c}d`` -> ``abd acd``, ``x{1..3}`` -> ``x1 x2 x3``; a
    group without a comma or a range (``{}``, ``{a}``) stays as written.

    :param word: a word without quotes
    :return: the words it expands to, in bash's order
    """
    depth, start = 0, -1
    for i, char in enumerate(word):
        if char == "{":
            depth += 1
            if depth == 1:
                start = i
        elif char == "}" and depth:
            depth -= 1
            if depth:
                continue
            body, head, tail = word[start + 1 : i], word[:start], word[i + 1 :]
            parts, level, begin = [], 0, 0
            for j, inner in enumerate(body):
                level += {"{": 1, "}": -1}.get(inner, 0)
                if inner == "," and level == 0:
                    parts.append(body[begin:j])
                    begin = j + 1
            parts.append(body[begin:])
            span = re.fullmatch(r"(-?\d+)\.\.(-?\d+)", body)
            if span:
                low, high = int(span.group(1)), int(span.group(2))
                parts = [str(n) for n in range(low, high + (1 if high >= low else -1), 1 if high >= low else -1)]
            elif len(parts) == 1:
                continue  # a literal group: bash leaves it, and so does the rest of this scan
            return [out for part in parts for out in expand_braces(head + part + tail)]
    return [word]


def shell_words(statement: list[str], variables: dict[str, str]) -> list[str]:
    """The words one command gets from a shell: variables substituted (not in single quotes), braces expanded (not in
    quotes), quotes removed.

    :param statement: tokens as :class:`shlex.shlex` splits them without removing quotes
    :param variables: the values of earlier ``NAME=value`` assignments; an unknown ``$NAME`` stays as written
    """
    words = []
    for token in statement:
        if not token.startswith("'"):
            token = _VARIABLE.sub(lambda m: variables.get(m.group(1), m.group(0)), token)
        pieces = expand_braces(token) if not any(q in token for q in "'\"") else [token]
        words += [shlex.split(piece)[0] if piece.strip("'\"") else "" for piece in pieces]
    return words


def statements(text: str) -> list[list[str]]:
    """The simple commands of some shell text, each as tokens with their quotes (``;``, ``&&``, ``||``, ``|`` and
    ``&`` separate them; ``#`` starts a comment)."""
    out: list[list[str]] = [[]]
    for line in text.replace("\\\n", " ").splitlines():  # a newline ends a command (a comment ends at it)
        lexer = shlex.shlex(line, posix=False, punctuation_chars=";&|")
        lexer.whitespace_split = True
        for token in lexer:
            if token in (";", "&&", "||", "|", "&"):
                out.append([])
            else:
                out[-1].append(token)
        out.append([])
    return [s for s in out if s]


def commands_of(text: str) -> list[list[str]]:
    """The ``sb3-graph`` commands of some shell text, as the words after ``sb3-graph``, after shell expansion.

    :param text: one fenced block's lines, or one inline span
    """
    variables: dict[str, str] = {}
    found = []
    for statement in statements(text):
        if statement[:1] in (["do"], ["then"], ["else"]):
            statement = statement[1:]
        if len(statement) >= 4 and statement[0] == "for" and statement[2] == "in":  # the loop's first round
            variables[statement[1]] = shell_words(statement[3:4], variables)[0]
            continue
        while statement and _ASSIGNMENT.match(statement[0]):
            name, value = statement.pop(0).split("=", 1)
            variables[name] = shell_words([value], variables)[0] if value else ""
        if statement[:1] == ["sb3-graph"]:
            words = statement[1:]
        elif len(statement) >= 3 and statement[0].startswith("python") and statement[1:3] == ["-m", "sb3_graph.cli"]:
            words = statement[3:]
        else:
            continue
        if any(w in ("...", "…") or w.endswith(("...", "…")) for w in words):
            continue  # a sketch, with an elision
        found.append(shell_words(words, variables))
    return found


def doc_commands(path: Path) -> list[tuple[int, str, list[str]]]:
    """Every ``sb3-graph`` command of one Markdown file.

    :return: (line, the command as written, its words after ``sb3-graph``) in file order
    """
    return markdown_commands(path.read_text(encoding="utf-8"))


def markdown_commands(text: str) -> list[tuple[int, str, list[str]]]:
    """Every ``sb3-graph`` command of some Markdown (see :func:`doc_commands`)."""
    found = []

    def line_of(offset: int) -> int:
        return text.count("\n", 0, offset) + 1

    for fence in _FENCE.finditer(text):
        if fence.group(1).strip().startswith(NOT_SHELL):
            continue
        for words in commands_of(fence.group(2)):
            found.append((line_of(fence.start(2)), "sb3-graph " + shlex.join(words), words))
    prose = _FENCE.sub(lambda m: "\n" * m.group(0).count("\n"), text)  # spans outside the fences, lines kept
    for span in _SPAN.finditer(prose):
        code = " ".join(span.group(1).split())
        if "sb3-graph " not in code and "sb3_graph.cli " not in code:
            continue
        for words in commands_of(code):
            if len(words) >= 2 or words[:1] in (["--help"], ["--version"]):  # `sb3-graph train` names the command
                found.append((prose.count("\n", 0, span.start()) + 1, code, words))
    return sorted(found, key=lambda item: item[0])


_LABEL = re.compile(r"^[A-Za-z0-9_.:@+-]+=")  # LABEL= in front of a planner spec


def placeholder(word: str) -> str | None:
    """A part of a word that stands for something the reader must fill in (``ENV``, ``FILE+shield``,
    ``<layout>``, ``RUN/best_model.zip``): a command with one does not run as written.

    :return: the part, or ``None``
    """
    if "<" in word or (">" in word and "->" not in word):
        return word
    for part in re.split(r"[/=:+,]", _LABEL.sub("", word, count=1)):
        stem = part.split(".")[0]
        if len(stem) >= 2 and re.fullmatch(r"[A-Z][A-Z0-9_]*", stem):
            return part
    return None


def parse_error(words: list[str]) -> str | None:
    """What the ``sb3-graph`` parser says of some words: ``None`` when it accepts them (``--help`` included), else its
    error line.

    :param words: the words after ``sb3-graph``
    """
    parser = build_parser()
    err = io.StringIO()
    with contextlib.redirect_stderr(err), contextlib.redirect_stdout(io.StringIO()):
        try:
            args, extra = parser.parse_known_args(words)
        except SystemExit as exit_info:
            return None if exit_info.code == 0 else err.getvalue().strip() or f"exit {exit_info.code}"
    if extra:
        return f"unrecognized arguments: {' '.join(extra)}"
    if getattr(args, "_missing", None):
        return f"unavailable: {args._missing}"
    return None


def example_commands() -> list[tuple[Path, int, str, list[str]]]:
    """The commands of the Examples page (written from the docstrings of ``examples/*.py`` at every build)."""
    sys.path.insert(0, str(ROOT / "docs" / "_ext"))
    import site_pages

    page = ROOT / "docs" / "examples.md"
    return [(page, line, code, words) for line, code, words in markdown_commands(site_pages.examples_page())]


COMMANDS = [(path, line, code, words) for path in markdown_files() for line, code, words in doc_commands(path)]
COMMANDS += example_commands()


def test_the_commands_are_found():
    # The pages hold many commands; each kind of place is searched: blocks, spans over two lines, python -m.
    assert len(COMMANDS) > 100
    assert any(path.name == "README.md" for path, *_ in COMMANDS)
    assert any(words[0] == "serve" for *_, words in COMMANDS)
    assert any("examples/aim_fast.py:AIMFast+shield" in words for *_, words in COMMANDS)  # the Examples page


def test_shell_expansion(tmp_path):
    assert expand_braces("--seed={0,1}") == ["--seed=0", "--seed=1"]
    assert expand_braces("a{b,{c,d}}e") == ["abe", "ace", "ade"]
    assert expand_braces("run{1..3}") == ["run1", "run2", "run3"]
    assert expand_braces("{x}") == ["{x}"] and expand_braces("{}") == ["{}"]
    assert commands_of("G=a/b.zip\nsb3-graph evaluate --planner $G+shield --planner '$G' # note\n") == [
        ["evaluate", "--planner", "a/b.zip+shield", "--planner", "$G"]
    ]
    assert commands_of("sb3-graph train --env-kwargs '{\"a\": 1}' \\\n  --seed {0,1}") == [
        ["train", "--env-kwargs", '{"a": 1}', "--seed", "0", "1"]
    ]
    assert commands_of("pip install -e . && sb3-graph evaluate; sb3-graph sweep ... --jobs 2") == [["evaluate"]]
    loop = "for K in 0 1; do\n  sb3-graph train --seed $K --out runs/s_$K\ndone"
    assert commands_of(loop) == [["train", "--seed", "0", "--out", "runs/s_0"]]
    page = tmp_path / "page.md"
    page.write_text(
        "Run `sb3-graph evaluate --planner\naim --seed 1`, or `sb3-graph train`.\n\n"
        "```bash\nsb3-graph export a.zip b.safetensors\n```\n\n```python\nprint('sb3-graph evaluate')\n```\n"
    )
    assert [(line, words) for line, _, words in doc_commands(page)] == [
        (1, ["evaluate", "--planner", "aim", "--seed", "1"]),
        (5, ["export", "a.zip", "b.safetensors"]),
    ]


@pytest.mark.parametrize(
    "words",
    [
        ["evaluate", "--planner", "aim", "--seed", "S"],  # a placeholder where a number belongs
        shell_words(shlex.split("evaluate --planner {aim,fifo}", posix=False), {}),  # braces leave a bare word
        ["evaluate", "--planner", "aim", "[--jobs", "N]"],  # a usage line
        ["evaluate", "--no-such-flag"],
        ["no-such-command"],
    ],
)
def test_a_broken_command_fails(words):
    assert parse_error(words) is not None


@pytest.mark.parametrize("word", ["ENV", "FILE+shield", "A1=FILE+shield", "zoo_configs/<file>.yml", "RUN/best.zip"])
def test_a_placeholder_is_found(word):
    assert placeholder(word) is not None


@pytest.mark.parametrize(
    "word", ["CoopIntersection4Way-v0", "GNN=envs/pretrained/x/best_model.safetensors+shield", "south->north", "aim"]
)
def test_a_real_word_is_no_placeholder(word):
    assert placeholder(word) is None


@pytest.mark.parametrize(
    "path,line,code,words", COMMANDS, ids=[f"{p.relative_to(ROOT)}:{line}" for p, line, _, _ in COMMANDS]
)
def test_every_command_parses(path, line, code, words):
    error = parse_error(words)
    assert error is None, f"{path.relative_to(ROOT)}:{line}: {code}\n{error}"
    filled = [part for part in map(placeholder, words) if part is not None]
    assert filled == [], f"{path.relative_to(ROOT)}:{line}: {code}\nplaceholders: {filled}"
