"""The code snippets of the user documentation, as the tests run them: a snippet is the
fenced ``python`` block right after an HTML comment ``<!-- snippet: NAME -->``."""

from __future__ import annotations

import re
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
#: Pages whose marked snippets the tests run.
PAGES = (REPO / "README.md", REPO / "docs" / "guide.md")

_SNIPPET = re.compile(r"<!-- snippet: ([\w-]+) -->\s*```python\n(.*?)```", re.S)


def snippets() -> dict[str, tuple[Path, str]]:
    """``{name: (page, code)}`` of every marked snippet."""
    out: dict[str, tuple[Path, str]] = {}
    for page in PAGES:
        for name, code in _SNIPPET.findall(page.read_text()):
            assert name not in out, f"snippet {name!r} twice"
            out[name] = (page, code)
    return out
