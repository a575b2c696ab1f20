"""The documentation stands alone: README.md and docs/ link only to files of the repository, the
README lists every document, and what a user reads (help texts) names no source file or thesis
equation, only the project's docs."""

import argparse
import re
from pathlib import Path

import pytest

from calibd.cli import build_parser as calibd_parser
from stim300.cli import build_parser as stim300_parser

ROOT = Path(__file__).resolve().parents[1]
DOCUMENTS = sorted([ROOT / "README.md", *(ROOT / "docs").glob("*.md")])
LINK = re.compile(r"\[[^\]]*\]\(([^)\s]+)\)")  # [text](target)
CITED_DOC = re.compile(r"\bdocs/[\w.-]+\.md\b")
FOREIGN_CITATION = re.compile(r"\.py\b|\beq\. ?[0-9]|\beqs?\. |[Ss]ection [0-9]|thesis [0-9]|§|\b[Ff]ig\. ?[0-9]")


def links(path: Path) -> list[str]:
    """Every markdown link target of a document, code blocks left out (they are not links)."""
    text = re.sub(r"```.*?```", "", path.read_text(encoding="utf-8"), flags=re.S)
    return LINK.findall(text)


def test_every_relative_link_resolves_inside_the_repository():
    broken = []
    for document in DOCUMENTS:
        for target in links(document):
            if re.match(r"[a-z]+:", target):
                continue
            file = (document.parent / target.split("#")[0]).resolve()
            if not file.is_relative_to(ROOT) or not file.exists():
                broken.append(f"{document.relative_to(ROOT)}: {target}")
    assert broken == []
    assert sum(len(links(d)) for d in DOCUMENTS) > 10  # the check has links to check


def test_no_link_leaves_the_repository_for_the_thesis_or_a_parent_folder():
    """The thesis is named in the docs (docs/method.md, Reference), never linked: a reader has the
    docs, not the thesis."""
    for document in DOCUMENTS:
        text = document.read_text(encoding="utf-8")
        assert "../" not in text, document.name
        assert not re.search(r"https?://\S*(thesis|unibo|amslaurea)", text, re.I), document.name


def test_every_docs_path_a_document_cites_exists():
    """`docs/NAME.md` written as code (not as a link) must name a document that exists too."""
    for document in DOCUMENTS:
        for cited in CITED_DOC.findall(document.read_text(encoding="utf-8")):
            assert (ROOT / cited).exists(), f"{document.name}: {cited}"


def test_the_readme_lists_every_document():
    readme = (ROOT / "README.md").read_text(encoding="utf-8")
    listed = readme[readme.index("## Documentation"):]
    listed = listed[:listed.index("\n## ", 1)] if "\n## " in listed[1:] else listed
    for document in (ROOT / "docs").glob("*.md"):
        assert f"](docs/{document.name})" in listed, document.name


def subcommand_parsers(parser: argparse.ArgumentParser):
    """The parser and every subcommand's, by name."""
    yield parser.prog, parser
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for name, sub in action.choices.items():
                yield f"{parser.prog} {name}", sub


@pytest.mark.parametrize("build", [calibd_parser, stim300_parser])
def test_help_texts_cite_the_projects_docs_not_source_files_or_equations(build):
    """A wheel ships no docs/ and no thesis, but a user can read the repository's docs; a source
    file or an equation number tells them nothing."""
    seen = 0
    for name, parser in subcommand_parsers(build()):
        text = parser.format_help()
        assert not FOREIGN_CITATION.search(text), f"{name}: {FOREIGN_CITATION.search(text).group()!r} in\n{text}"
        for cited in CITED_DOC.findall(text):
            assert (ROOT / cited).exists(), f"{name}: {cited}"
        seen += 1
    assert seen > 4
