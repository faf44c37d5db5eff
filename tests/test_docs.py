"""The README quotes figures from the docs: each must be the one its doc states (issue 38)."""

import re
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
_NUMBER = re.compile(r"(?<![\w.])\d+(?:\.\d+)?(?![\w.])")


def _results_rows() -> list[tuple[str, str, list[Path]]]:
    """(experiment, thermofield's figures, the docs linked) for each row of the README's results table."""
    readme = (ROOT / "README.md").read_text()
    table = readme.split("## Results", 1)[1].split("\n\n", 2)[1]
    rows = []
    for line in table.splitlines()[2:]:
        cells = [cell.strip() for cell in line.strip().strip("|").split("|")]
        links = [ROOT / target.split("#")[0] for target in re.findall(r"\]\(([^)]+)\)", cells[-1])]
        rows.append((cells[0], cells[2], links))
    return rows


def _numbers(text: str) -> set[str]:
    return set(_NUMBER.findall(text))


def _roundings(text: str) -> set[str]:
    """Every number of ``text`` as written and rounded to 0..3 decimals (a README may quote 115.9 as 116)."""
    stated = set()
    for number in _NUMBER.findall(text):
        stated.add(number)
        decimals = len(number.split(".")[1]) if "." in number else 0
        stated.update(f"{float(number):.{d}f}" for d in range(min(decimals, 4)))
    return stated


def test_every_figure_the_readme_quotes_is_in_the_doc_it_links():
    rows = _results_rows()
    assert len(rows) >= 10
    missing = {}
    for experiment, figures, links in rows:
        assert links and all(link.is_file() for link in links), experiment
        stated = set().union(*(_roundings(link.read_text()) for link in links))
        absent = sorted(_numbers(figures) - stated)
        if absent:
            missing[experiment] = absent
    assert missing == {}, "README figures that their docs do not state"


def test_the_docs_index_links_every_page():
    index = (ROOT / "docs" / "README.md").read_text()
    linked = {target.split("#")[0] for target in re.findall(r"\]\(([^)]+\.md)[^)]*\)", index)}
    pages = {path.name for path in (ROOT / "docs").glob("*.md")} - {"README.md"}
    assert pages - linked == set(), "pages a newcomer cannot find from docs/README.md"
