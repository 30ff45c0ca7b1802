"""The documentation's references resolve: relative links between pages, and the code's citations of
docs/method.md sections."""
import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PAGES = [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md")), ROOT / "results" / "README.md",
         *sorted((ROOT / "results").glob("*/README.md"))]
LINK = re.compile(r"\]\(([^)\s]+)\)")


def relative_links(text: str) -> list[str]:
    """The link targets of a markdown text that point into the repository (no URLs, no in-page anchors)."""
    targets = [t.split("#")[0] for t in LINK.findall(text)]
    return [t for t in targets if t and not re.match(r"^[a-z]+:", t)]


def test_the_link_reader_finds_relative_targets_only():
    text = "see [a](docs/a.md), [b](../b/README.md#part), [c](https://x.org/y), [d](#top) and ![e](fig.png)"
    assert relative_links(text) == ["docs/a.md", "../b/README.md", "fig.png"]


@pytest.mark.parametrize("page", PAGES, ids=lambda p: str(p.relative_to(ROOT)))
def test_every_relative_link_of_a_page_exists(page):
    missing = [t for t in relative_links(page.read_text()) if not (page.parent / t).exists()]
    assert not missing, f"{page.relative_to(ROOT)} links to missing files: {missing}"


def test_every_cited_method_section_exists():
    sections = {int(n) for n in re.findall(r"^## (\d+)\. ", (ROOT / "docs" / "method.md").read_text(), re.M)}
    assert sections == set(range(1, 10))
    cited = {}
    for folder in ("torchrl_reset", "envs", "recipes", "tests"):
        for path in (ROOT / folder).rglob("*"):
            if path.suffix in (".py", ".yaml"):
                for n in re.findall(r"method\.md\)? section (\d+)", path.read_text()):
                    cited.setdefault(int(n), []).append(str(path.relative_to(ROOT)))
    assert cited, "the code cites docs/method.md"
    assert set(cited) <= sections, {n: where for n, where in cited.items() if n not in sections}
