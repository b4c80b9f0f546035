"""ARCHITECTURE.md is how a newcomer finds a room without a guide: each package's paragraph
(`**`keo_service.<package>`**`) names every module of that package, so a module added
without a word about where it belongs fails here; and the drawing keeps live, sim and
offline side by side on one floor, as the import contracts have them."""

from __future__ import annotations

import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
DOC = (ROOT / "ARCHITECTURE.md").read_text(encoding="utf-8")
GENERATED = {"egm_pb2"}  # protoc's output, named with its .proto in the adapters' paragraph


def _paragraphs() -> dict[str, str]:
    """Each package's text: from its bold name to the next package's (or the next heading)."""
    heads = [
        (m.start(), m.group(1))
        for m in re.finditer(r"^\*\*`keo_service\.(\w+)`\*\*", DOC, flags=re.MULTILINE)
    ]
    out = {}
    for i, (start, package) in enumerate(heads):
        end = heads[i + 1][0] if i + 1 < len(heads) else DOC.index("\n## ", start)
        out[package] = DOC[start:end]
    return out


PACKAGES = sorted(p.name for p in (ROOT / "keo_service").iterdir() if (p / "__init__.py").is_file())


def test_every_package_has_a_paragraph():
    assert set(_paragraphs()) == set(PACKAGES)


@pytest.mark.parametrize("package", PACKAGES)
def test_the_paragraph_names_every_module(package):
    text = _paragraphs()[package]
    modules = sorted(
        f.stem
        for f in (ROOT / "keo_service" / package).glob("*.py")
        if f.stem != "__init__" and f.stem not in GENERATED
    )
    assert modules
    missing = [m for m in modules if not re.search(rf"`(?:[\w.]*\.)?{m}(?:[`.(:]|\b)", text)]
    assert not missing, f"ARCHITECTURE.md's keo_service.{package} paragraph lacks {missing}"


def test_live_sim_and_offline_are_drawn_as_siblings():
    """In the drawing the three sit on one line, below adapters and above io."""
    drawing = DOC[DOC.index("```") : DOC.index("```", DOC.index("```") + 3)]
    rows = drawing.splitlines()
    row = next(i for i, line in enumerate(rows) if "keo_service.live" in line)
    assert "keo_service.sim" in rows[row]
    assert "keo_service.offline" in rows[row]
    above = "\n".join(rows[:row])
    below = "\n".join(rows[row + 1 :])
    assert "keo_service.adapters" in above
    assert "keo_service.io" in below
