"""The README's results block, generated from the paper report so the two never disagree.

`results_block(report)` takes the text of `report/REPORT.md` and returns the README block:
the report's Table 1 (Safe-CDT at the budget on every pair, the paper's numbers beside ours),
the tally of the paper's claims, and the line saying when, where and with what command the
report was made. `sync_readme` writes it between the README's two markers;
`python -m safecdt_jax.paper.readme` does that for this repository after `safecdt-jax paper`.
"""

from __future__ import annotations

import os
import re
import sys
from pathlib import Path

START, END = "<!-- results:start (generated from report/REPORT.md) -->", "<!-- results:end -->"


def _section(report: str, heading: str) -> tuple[str, str]:
    """(title, body) of the `## heading...` section of a markdown report (to the next `## `)."""
    match = re.search(rf"^## ({re.escape(heading)}.*?)$(.*?)(?=^## |\Z)", report, re.M | re.S)
    if match is None:
        raise ValueError(f"the report has no section '## {heading}'")
    return match.group(1).strip(), match.group(2).strip()


def results_block(report: str) -> str:
    """The README block (markdown, without the markers) made from a REPORT.md text."""
    generated = re.search(r"^- Generated (.+?);", report, re.M)
    tally = re.search(r"Claims supported: (\d+), not supported: (\d+), not run: (\d+)", report)
    if generated is None or tally is None:
        raise ValueError("the report lacks its 'Generated ...' line or its claims tally")
    title, table = _section(report, "Table 1")
    ok, no, missing = tally.groups()
    return (f"**{title}**, from [the report](report/REPORT.md) (`safecdt-jax paper`, generated "
            f"{generated.group(1)}; the paper's section-5 claims: {ok} supported, {no} not, "
            f"{missing} not run). {table}")


def sync_readme(readme: str | os.PathLike, report: str | os.PathLike) -> bool:
    """Replace the block between the README's markers with `results_block` of the report;
    returns whether the README changed. ValueError if the README lacks the markers."""
    from safecdt_jax.io import write_text_atomic

    text = Path(readme).read_text()
    if START not in text or END not in text:
        raise ValueError(f"{os.fspath(readme)} lacks the results markers {START} ... {END}")
    head, rest = text.split(START, 1)
    _, tail = rest.split(END, 1)
    new = f"{head}{START}\n{results_block(Path(report).read_text())}\n{END}{tail}"
    if new != text:
        write_text_atomic(readme, new)
    return new != text


if __name__ == "__main__":
    root = Path(sys.argv[1]) if len(sys.argv) > 1 else Path(".")
    changed = sync_readme(root / "README.md", root / "report" / "REPORT.md")
    print("README.md updated" if changed else "README.md already matches the report")
