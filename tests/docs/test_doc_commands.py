"""Every `vcfusion ...` command line shown in README.md and docs/ parses with the real parser, so a
renamed or removed option breaks this test, not a reader."""

from __future__ import annotations

import re
import shlex
from pathlib import Path

import pytest

from vcfusion.commands import build_parser

ROOT = Path(__file__).resolve().parents[2]
# docs/incoming/: pages of other branches waiting to be folded in; reference/cli.md lists usage lines
EXCLUDED = ("docs/incoming/", "docs/reference/cli.md")
# commands the docs show that the parser gains when the `commands` package lands; until the parser
# has them they are skipped (named in the skip reason), afterwards they are parsed like the others
ADDED_WITH_COMMANDS_PACKAGE = ("scenarios", "--version")

FENCE = re.compile(r"^\s*(```|~~~)")
COMMAND = re.compile(r"(?:^|[\s;&|(])vcfusion(\s.*)?$")


def doc_files() -> list[Path]:
    files = [ROOT / "README.md", *sorted((ROOT / "docs").rglob("*.md"))]
    return [f for f in files if not any(f.relative_to(ROOT).as_posix().startswith(e) for e in EXCLUDED)]


def code_lines(text: str) -> list[tuple[int, str]]:
    """(line number, logical line) of the fenced code blocks: continuations joined, comments gone."""
    out, inside, buffer, start = [], False, "", 0
    for number, line in enumerate(text.splitlines(), 1):
        if FENCE.match(line):
            inside = not inside
            buffer = ""
            continue
        if not inside:
            continue
        if not buffer:
            start = number
        if line.rstrip().endswith("\\"):
            buffer += line.rstrip()[:-1] + " "
            continue
        out.append((start, buffer + line))
        buffer = ""
    return out


def commands_in(path: Path) -> list[tuple[int, list[str]]]:
    """(line, argv after `vcfusion`) of each vcfusion command line in the file's code blocks."""
    found = []
    for number, line in code_lines(path.read_text(encoding="utf-8")):
        try:
            words = shlex.split(line, comments=True)
        except ValueError:  # not shell (a YAML or Python line with an odd quote)
            continue
        joined = " ".join(words)
        if COMMAND.search(joined) is None or "-m vcfusion" in joined:
            continue
        # the words after the last `vcfusion` word, each as the shell would pass it (quoted
        # words with spaces stay one word)
        at = max(i for i, word in enumerate(words) if COMMAND.search(word))
        argv = words[at + 1:]
        # a shell loop's body or a command list: stop at the shell's own separators
        for i, word in enumerate(argv):
            if word in (";", "&&", "||", "|", "done"):
                argv = argv[:i]
                break
        found.append((number, argv))
    return found


CASES = [(f"{f.relative_to(ROOT).as_posix()}:{n}", argv) for f in doc_files() for n, argv in commands_in(f)]


def test_the_docs_show_commands():
    # the extraction finds the README's commands (an empty list would pass every case below)
    assert any(where.startswith("README.md") for where, _ in CASES)
    assert len(CASES) >= 20


@pytest.mark.parametrize("where,argv", CASES, ids=[w for w, _ in CASES])
def test_command_parses(where, argv, capsys):
    parser = build_parser()
    if argv and argv[0] in ADDED_WITH_COMMANDS_PACKAGE:
        known = {a for action in parser._actions for a in getattr(action, "option_strings", [])}
        sub = next(a for a in parser._actions if a.__class__.__name__ == "_SubParsersAction")
        if argv[0] not in known and argv[0] not in sub.choices:
            pytest.skip(f"`vcfusion {argv[0]}` comes with the commands package")
    try:
        parser.parse_args(argv)
    except SystemExit as exc:
        if argv and argv[0] == "--version" and exc.code == 0:
            return
        err = capsys.readouterr().err.strip().splitlines()
        pytest.fail(f"{where}: `vcfusion {' '.join(argv)}` does not parse: {err[-1] if err else exc}")


def test_extraction_joins_continuations_and_drops_comments():
    text = "```sh\nvcfusion run s.yaml \\\n    --seed 3   # one run\n# vcfusion nothing\n```\nvcfusion prose\n"
    assert [(n, " ".join(line.split())) for n, line in code_lines(text)] == [
        (2, "vcfusion run s.yaml --seed 3 # one run"), (4, "# vcfusion nothing")]
    tmp = ROOT / "tests" / "docs"
    path = tmp / ".probe.md"
    try:
        path.write_text(text)
        assert commands_in(path) == [(2, ["run", "s.yaml", "--seed", "3"])]
    finally:
        path.unlink()


def test_readme_is_a_front_page():
    lines = (ROOT / "README.md").read_text(encoding="utf-8").splitlines()
    assert len(lines) <= 300, f"README.md has {len(lines)} lines; the detail belongs in docs/"
