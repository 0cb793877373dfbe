"""README's measured figures are RESULTS.md's and BENCHMARKS.md's, with the same value.

The convention (README, "Layout"): a figure README quotes as a measurement is a link whose text is the figure and
whose target is the section of RESULTS.md or BENCHMARKS.md that holds it, ``[0.73 ms](BENCHMARKS.md#per-muscle-...)``.
The check: the section exists, and the figure's text appears in it or in the summary-table row that links to it,
character for character (bold markers and line breaks aside). A figure changed on one side only fails here.
"""
from __future__ import annotations

import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
CLAIM = re.compile(r"\[([0-9][^\]]*)\]\((RESULTS|BENCHMARKS)\.md#([a-z0-9-]+)\)")


def slug(heading: str) -> str:
    """GitHub's anchor of a Markdown heading: lower case, punctuation dropped, spaces to hyphens."""
    return re.sub(r"[^a-z0-9 -]", "", heading.strip().lower()).replace(" ", "-")


def flat(text: str) -> str:
    return " ".join(text.replace("**", "").split())


def sections(path: Path) -> dict[str, str]:
    """anchor -> the section's text (its heading to the next heading of any level), plus the lines elsewhere in the
    file that link to it (the summary table's rows), flattened."""
    text = path.read_text()
    parts = re.split(r"^#{1,6} (.+)$", text, flags=re.M)
    found = {slug(heading): body for heading, body in zip(parts[1::2], parts[2::2])}
    for anchor in found:
        rows = [line for line in text.splitlines() if f"(#{anchor})" in line]
        found[anchor] = flat(found[anchor] + "\n" + "\n".join(rows))
    return found


def held_figure(figure: str, text: str) -> bool:
    """``figure`` in ``text`` as a whole number: "16 %" is not held by "0.16 %" nor "2.4" by "2.42"."""
    return re.search(r"(?<![0-9.])" + re.escape(figure) + r"(?![0-9])", text) is not None


def claims() -> list[tuple[str, str, str]]:
    return CLAIM.findall((ROOT / "README.md").read_text())


def test_readme_quotes_figures_by_the_convention():
    """The convention is in use (a README without any marked figure would pass the check below vacuously)."""
    assert len(claims()) >= 10


@pytest.mark.parametrize("figure, doc, anchor", claims())
def test_a_readme_figure_is_the_one_its_section_holds(figure, doc, anchor):
    held = sections(ROOT / f"{doc}.md")
    assert anchor in held, f"README links {doc}.md#{anchor}, which is no heading of {doc}.md"
    assert held_figure(flat(figure), held[anchor]), f"README quotes {figure!r}; {doc}.md#{anchor} does not hold it"


def test_the_check_fails_on_a_figure_its_section_does_not_hold():
    assert held_figure("16 %", "a residual of 0.0010 N m (16 %)") and held_figure("0.73 ms", "batch 1 0.73 ms")
    assert not held_figure("16 %", "0.16 %") and not held_figure("3 ms", "0.73 ms")
    assert not held_figure("2.4", "2.42-2.44 ms") and not held_figure("0.42 %", "0.43 %")
