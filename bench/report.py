"""Benchmark tables as plain data, rendered either for the terminal (rich) or as Markdown.

Keeping the numbers as pre-formatted strings in one structure guarantees that
the terminal output and docs/benchmarks/*.md show exactly the same cells.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field

from rich.table import Table


@dataclass
class ReportTable:
    title: str
    columns: list[str]
    rows: list[list[str]] = field(default_factory=list)
    # Row indices after which a horizontal rule separates groups of rows.
    section_ends: set[int] = field(default_factory=set)
    notes: list[str] = field(default_factory=list)

    def add_row(self, *cells: str, end_section: bool = False) -> None:
        if len(cells) != len(self.columns):
            raise ValueError(f"{self.title}: row has {len(cells)} cells for {len(self.columns)} columns")
        self.rows.append(list(cells))
        if end_section:
            self.section_ends.add(len(self.rows) - 1)

    def end_section(self) -> None:
        if self.rows:
            self.section_ends.add(len(self.rows) - 1)

    def column(self, name: str) -> list[str]:
        i = self.columns.index(name)
        return [row[i] for row in self.rows]


def fmt(value: float, digits: int = 2) -> str:
    """Fixed decimals for ordinary errors; scientific where fixed decimals would show 0.00 (noise-free runs)."""
    if value is None or not math.isfinite(value):
        return "-"
    if value != 0 and abs(value) < 0.5 * 10**-digits:
        return f"{value:.1e}"
    return f"{value:.{digits}f}"


def fmt_pair(mean: float, median: float) -> str:
    return f"{fmt(mean)} ({fmt(median)})"


def yes_no(ok: bool | None) -> str:
    return "-" if ok is None else ("yes" if ok else "NO")


def to_rich(table: ReportTable) -> Table:
    out = Table(title=table.title, title_justify="left", caption="\n".join(table.notes) or None, caption_justify="left")
    for i, name in enumerate(table.columns):
        # Wrap rather than truncate on a narrow terminal: a cut-off number is worse than a tall row.
        out.add_column(name, justify="left" if i == 0 else "right", overflow="fold")
    for i, row in enumerate(table.rows):
        out.add_row(*row, end_section=i in table.section_ends)
    return out


def _escape_md(cell: str) -> str:
    return cell.replace("|", "\\|")


def to_markdown(table: ReportTable) -> str:
    lines = [f"### {table.title}", ""]
    lines.append("| " + " | ".join(_escape_md(c) for c in table.columns) + " |")
    lines.append("|" + "|".join(["---"] + ["---:"] * (len(table.columns) - 1)) + "|")
    lines.extend("| " + " | ".join(_escape_md(c) for c in row) + " |" for row in table.rows)
    for note in table.notes:
        lines.extend(["", note])
    return "\n".join(lines) + "\n"


def markdown_document(title: str, header: Sequence[str], tables: Iterable[ReportTable]) -> str:
    parts = [f"# {title}", "", *(f"- {line}" for line in header), ""]
    parts.extend(to_markdown(t) for t in tables)
    return "\n".join(parts)
