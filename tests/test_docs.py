"""The README and the command-line manual stay short and true to the parser, no link in the
docs points nowhere, and the benchmarks' README stays a short set of current tables whose
results files it cites."""

from __future__ import annotations

import argparse
import re
from pathlib import Path

import pytest

from snds.cli import build_parser

ROOT = Path(__file__).resolve().parents[1]
README = ROOT / "README.md"
BENCHMARKS = ROOT / "benchmarks" / "README.md"
PAGES = [README, BENCHMARKS, *sorted((ROOT / "docs").glob("*.md"))]
MAX_README_LINES = 160
MAX_BENCHMARKS_LINES = 400

FENCE = re.compile(r"^```.*?^```", re.MULTILINE | re.DOTALL)
INLINE_CODE = re.compile(r"`[^`\n]*`")
# [text](target) and ![alt](target); the target ends at whitespace (a title may follow) or ')'.
LINK = re.compile(r"!?\[[^\]\n]*\]\(\s*<?([^)\s>]+)>?(?:\s+\"[^\"]*\")?\s*\)")
HTML_SRC = re.compile(r"<(?:img|a)\b[^>]*?(?:src|href)=\"([^\"]+)\"", re.IGNORECASE)
LONG_OPTION = re.compile(r"(?<![\w-])--[a-z][a-z0-9-]*")


def _code_blocks(text: str) -> list[str]:
    return [block.split("\n", 1)[1].rsplit("```", 1)[0] for block in FENCE.findall(text)]


def _quick_reference(text: str) -> dict[str | None, set[str]]:
    """Long options named per subcommand (None: the global ones) in the README's code blocks.

    A line `snds [GLOBAL] SUB ...` starts a command; indented lines that follow continue it;
    any other line ends it. Comments (after ` #`) are not read.
    """
    subcommands = set(_subparsers().choices)
    named: dict[str | None, set[str]] = {}
    for block in _code_blocks(text):
        current: str | None | bool = False  # False: not inside a snds command
        for raw in block.splitlines():
            words = raw.split(" #", 1)[0].split()
            if words[:1] == ["snds"] or words[:3] == ["python", "-m", "snds"]:
                rest = words[1:] if words[0] == "snds" else words[3:]
                at = next((i for i, w in enumerate(rest) if w in subcommands), len(rest))
                current = rest[at] if at < len(rest) else None
                named.setdefault(None, set()).update(LONG_OPTION.findall(" ".join(rest[:at])))
                if current is not None:
                    options = LONG_OPTION.findall(" ".join(rest[at + 1 :]))
                    named.setdefault(current, set()).update(options)
            elif current is not False and raw[:1].isspace() and words:
                named.setdefault(current, set()).update(LONG_OPTION.findall(" ".join(words)))
            else:
                current = False
    return named


def _subparsers() -> argparse._SubParsersAction:
    parser = build_parser()
    return next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))


def test_readme_is_short():
    lines = README.read_text().count("\n")
    assert lines <= MAX_README_LINES, f"README.md has {lines} lines, at most {MAX_README_LINES}"


def test_benchmarks_readme_is_short_and_current():
    text = BENCHMARKS.read_text()
    lines = text.count("\n")
    assert lines <= MAX_BENCHMARKS_LINES, f"benchmarks/README.md has {lines} lines"
    assert not re.search(r"\bstale\b", text, flags=re.IGNORECASE), "a table marked stale"


def test_benchmark_results_are_cited():
    # GIVEN what benchmarks/results holds (a file, or a folder, by name without its suffix)
    text = BENCHMARKS.read_text()
    results = BENCHMARKS.parent / "results"
    entries = sorted(results.iterdir()) if results.is_dir() else []
    # THEN the README cites each, so nothing is kept that no table reads
    uncited = [p.name for p in entries if f"results/{p.name.split('.')[0]}" not in text]
    assert not uncited, f"benchmarks/results holds files no table cites: {uncited}"


def test_readme_cli_reference_matches_the_parser():
    # GIVEN the commands and options the README's code blocks name
    named = _quick_reference(README.read_text())
    subparsers = _subparsers()
    # THEN every subcommand of the parser is named, and no other
    assert set(subparsers.choices) <= set(named), set(subparsers.choices) - set(named)
    unknown_subcommands = {sub for sub in named if sub is not None} - set(subparsers.choices)
    assert not unknown_subcommands
    # AND every option named for a subcommand is in that subcommand's --help
    global_help = build_parser().format_help()
    for sub, options in named.items():
        help_text = global_help if sub is None else subparsers.choices[sub].format_help()
        accepted = set(LONG_OPTION.findall(help_text))
        missing = sorted(options - accepted)
        assert not missing, f"README names {missing} for `snds {sub or ''}`, the parser lacks them"


def test_cli_manual_shows_every_subcommands_current_usage(monkeypatch):
    # GIVEN the usage blocks of docs/cli.md, and the parser's usage at the width they use
    monkeypatch.setenv("COLUMNS", "80")
    parser = build_parser()
    subparsers = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
    blocks = {}
    for block in _code_blocks((ROOT / "docs" / "cli.md").read_text()):
        if block.startswith("usage: snds "):
            word = block.split()[2]
            blocks[None if word.startswith("[") else word] = block.strip()
    # THEN the manual has one for the program and each subcommand
    assert set(blocks) == {None, *subparsers.choices}
    # AND each is what `snds [SUB] --help` prints, so the manual cannot fall behind the parser
    for sub, block in blocks.items():
        usage = (parser if sub is None else subparsers.choices[sub]).format_usage().strip()
        assert block == usage, f"docs/cli.md's usage of `snds {sub or ''}` is out of date"


def _slug(heading: str) -> str:
    """GitHub's anchor of a heading: lower case, punctuation dropped, spaces to hyphens."""
    text = INLINE_CODE.sub(lambda m: m.group(0)[1:-1], heading.strip()).lower()
    text = re.sub(r"[^\w\- ]", "", text)
    return text.replace(" ", "-")


def _anchors(path: Path) -> set[str]:
    text = FENCE.sub("", path.read_text())
    anchors: set[str] = set()
    for heading in re.findall(r"^#{1,6}\s+(.+?)\s*#*$", text, flags=re.MULTILINE):
        slug, n = _slug(heading), 0
        while (slug if n == 0 else f"{slug}-{n}") in anchors:
            n += 1
        anchors.add(slug if n == 0 else f"{slug}-{n}")
    return anchors


def _links(path: Path) -> list[str]:
    text = INLINE_CODE.sub("", FENCE.sub("", path.read_text()))
    return LINK.findall(text) + HTML_SRC.findall(text)


@pytest.mark.parametrize("page", PAGES, ids=lambda p: str(p.relative_to(ROOT)))
def test_relative_links_resolve(page):
    broken = []
    for target in _links(page):
        if re.match(r"^[a-z][a-z0-9+.-]*:", target, flags=re.IGNORECASE):
            continue  # http:, https:, mailto: ...
        file, _, fragment = target.partition("#")
        resolved = (page.parent / file).resolve() if file else page
        if not resolved.exists():
            broken.append(target)
        elif fragment and resolved.suffix == ".md" and fragment not in _anchors(resolved):
            broken.append(target)
    assert not broken, f"{page.relative_to(ROOT)}: links to nothing: {broken}"


def test_readme_python_example_runs(monkeypatch):
    # GIVEN the README's Python block, with a short budget and a small check
    block = README.read_text().split("```python\n", 1)[1].split("```", 1)[0]
    import snds

    train, check = snds.TrainConfig, snds.CheckConfig
    short = lambda **kw: train(**{**kw, "steps": 200})  # noqa: E731
    small = lambda **kw: check(rollouts=5, samples=100)  # noqa: E731
    monkeypatch.setattr(snds, "TrainConfig", short)
    monkeypatch.setattr(snds, "CheckConfig", small)
    # WHEN it runs
    scope: dict = {}
    exec(compile(block, "README.md", "exec"), scope)
    # THEN it made what it says: a stable policy's metrics, and velocities in user units
    assert scope["metrics"].stability.samples_checked == 100
    assert scope["velocities"].shape == scope["demos"][0].states.shape
