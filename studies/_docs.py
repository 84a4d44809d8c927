"""Writing a script's results into the docs: one section of a markdown file, replaced in place."""

import re
from pathlib import Path


def replace_section(path: Path, heading: str, body: str, keep_subsections: bool = False) -> None:
    """Replace what follows the line ``heading`` (e.g. ``"## Soak"``) in ``path`` with ``body``, up to the next
    heading of the same level or higher (``keep_subsections``: up to the next heading of any level, so hand-written
    ``###`` notes below a generated table survive); append the section if ``path`` lacks it."""
    doc = path.read_text()
    section = f"{heading}\n\n{body.rstrip()}\n"
    if heading not in doc:
        path.write_text(doc.rstrip() + "\n\n" + section)
        return
    head, rest = doc.split(heading, 1)
    nxt = re.search(r"^#{2,} " if keep_subsections else r"^## ", rest, flags=re.M)
    path.write_text(head + section + ("\n" + rest[nxt.start():] if nxt else ""))
