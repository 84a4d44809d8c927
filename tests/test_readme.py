"""The README's links lead somewhere, and each headline result in its table is the figure the linked doc holds."""

import pathlib
import re

ROOT = pathlib.Path(__file__).resolve().parent.parent
README = (ROOT / "README.md").read_text()


def test_every_relative_link_exists():
    links = re.findall(r"\]\(([^)#]+)(?:#[^)]*)?\)", README)
    assert links
    missing = [link for link in links if not link.startswith("http") and not (ROOT / link).exists()]
    assert not missing, missing


def test_each_headline_result_appears_in_the_doc_it_links():
    table = README.split("## Results", 1)[1].split("\n## ", 1)[0]
    rows = [line for line in table.splitlines() if line.startswith("| ") and "](" in line]
    assert len(rows) >= 4
    for row in rows:
        result = row.split("|")[2]
        figure = re.search(r"\d[\d.,]*", result).group()
        doc = re.search(r"\]\(([^)]+)\)", row).group(1)
        assert figure in (ROOT / doc).read_text(), f"{figure!r} ({row.strip()}) is not in {doc}"
