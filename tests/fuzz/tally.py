"""How many cases the fuzzer tried, and what came of them, by caller and operation; printed after the run.

"Zero 5xx" means little without the number of requests behind it, so every test that sends a generated or
curated request records it here (`record`), and tests/fuzz/conftest.py prints the table at the end of the
session. Counts include the replays Hypothesis makes while shrinking a failure, so they count requests sent.
"""

from __future__ import annotations

from collections import Counter, defaultdict
from collections.abc import Iterable
from dataclasses import dataclass, field


@dataclass
class Row:
    cases: int = 0
    kinds: Counter[str] = field(default_factory=Counter)
    """positive / negative, and the schemathesis phase (examples, coverage, fuzzing) or "curated"."""
    statuses: Counter[str] = field(default_factory=Counter)
    """2xx, 3xx, 4xx, 5xx."""
    failures: int = 0


class Tally:
    def __init__(self) -> None:
        self.rows: defaultdict[tuple[str, str], Row] = defaultdict(Row)

    def record(self, category: str, operation: str, *, kinds: Iterable[str], status: int | None) -> None:
        row = self.rows[(category, operation)]
        row.cases += 1
        row.kinds.update(kinds)
        if status is not None:
            row.statuses[f"{status // 100}xx"] += 1

    def failed(self, category: str, operation: str) -> None:
        self.rows[(category, operation)].failures += 1

    def lines(self) -> list[str]:
        if not self.rows:
            return []
        width = max(len(operation) for _, operation in self.rows)
        header = (
            f"{'operation':<{width}}  {'cases':>6}  {'pos':>5}  {'neg':>5}  {'2xx':>5}  {'4xx':>5}  {'5xx':>4}  fail"
        )
        out: list[str] = []
        for category in sorted({c for c, _ in self.rows}):
            rows = {op: row for (c, op), row in self.rows.items() if c == category}
            total = Row()
            out += ["", f"[{category}]", header]
            for operation in sorted(rows):
                row = rows[operation]
                out.append(self._line(operation, row, width))
                total.cases += row.cases
                total.kinds.update(row.kinds)
                total.statuses.update(row.statuses)
                total.failures += row.failures
            phases = ", ".join(f"{k} {n}" for k, n in sorted(total.kinds.items()) if k not in ("positive", "negative"))
            out.append(self._line("total", total, width) + (f"   ({phases})" if phases else ""))
        cases = sum(r.cases for r in self.rows.values())
        failures = sum(r.failures for r in self.rows.values())
        server_errors = sum(r.statuses["5xx"] for r in self.rows.values())
        out += ["", f"all categories: {cases} cases, {server_errors} answered 5xx, {failures} failed a check"]
        return out

    @staticmethod
    def _line(operation: str, row: Row, width: int) -> str:
        s = row.statuses
        return (
            f"{operation:<{width}}  {row.cases:>6}  {row.kinds['positive']:>5}  {row.kinds['negative']:>5}  "
            f"{s['2xx']:>5}  {s['4xx']:>5}  {s['5xx']:>4}  {row.failures:>4}"
        )


TALLY = Tally()
