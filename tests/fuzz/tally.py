"""How many cases the fuzzer tried, and what came of them, by caller and operation; printed after the run.

"Zero 5xx" means little without the number of requests behind it, so every test that sends a generated or
curated request records it here (`record`), and tests/fuzz/conftest.py prints the table at the end of the
session. Counts include the replays Hypothesis makes while shrinking a failure, so they count requests sent.

A request can also end without a status: an exception raised inside the in-process app (the test client
re-raises it instead of answering 500) is counted as an exception, a failure as bad as a 5xx; a real server that
closed the connection without an answer (a protocol abuse it refused) is counted as "closed".
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
    statuses: Counter[int] = field(default_factory=Counter)
    """Each status code answered."""
    exceptions: Counter[str] = field(default_factory=Counter)
    """Exceptions raised instead of an answer, by type."""
    closed: int = 0
    """Connections a real server closed without answering."""
    failures: int = 0

    def add(self, other: Row) -> None:
        self.cases += other.cases
        self.kinds.update(other.kinds)
        self.statuses.update(other.statuses)
        self.exceptions.update(other.exceptions)
        self.closed += other.closed
        self.failures += other.failures

    def by_class(self, hundreds: int) -> int:
        return sum(n for status, n in self.statuses.items() if status // 100 == hundreds)


class Tally:
    def __init__(self) -> None:
        self.rows: defaultdict[tuple[str, str], Row] = defaultdict(Row)

    def record(
        self,
        category: str,
        operation: str,
        *,
        kinds: Iterable[str],
        status: int | None,
        exception: BaseException | None = None,
    ) -> None:
        """One request: its status, or the exception raised instead (status None and no exception: closed)."""
        row = self.rows[(category, operation)]
        row.cases += 1
        row.kinds.update(kinds)
        if status is not None:
            row.statuses[status] += 1
        elif exception is not None:
            row.exceptions[type(exception).__name__] += 1
        else:
            row.closed += 1

    def failed(self, category: str, operation: str) -> None:
        self.rows[(category, operation)].failures += 1

    def total(self) -> Row:
        total = Row()
        for row in self.rows.values():
            total.add(row)
        return total

    def lines(self) -> list[str]:
        if not self.rows:
            return []
        width = max(len(operation) for _, operation in self.rows)
        header = (
            f"{'operation':<{width}}  {'cases':>6}  {'pos':>5}  {'neg':>5}  {'2xx':>5}  {'4xx':>5}  {'5xx':>4}  "
            f"{'exc':>4}  fail"
        )
        out: list[str] = []
        for category in sorted({c for c, _ in self.rows}):
            rows = {op: row for (c, op), row in self.rows.items() if c == category}
            total = Row()
            out += ["", f"[{category}]", header]
            for operation in sorted(rows):
                out.append(self._line(operation, rows[operation], width))
                total.add(rows[operation])
            phases = ", ".join(f"{k} {n}" for k, n in sorted(total.kinds.items()) if k not in ("positive", "negative"))
            out.append(self._line("total", total, width) + (f"   ({phases})" if phases else ""))
        return out + ["", *self.summary()]

    def summary(self) -> list[str]:
        """The whole run in three lines: cases and answers by class, 4xx by status, 5xx and exceptions."""
        total = self.total()
        four = ", ".join(f"{status}: {n}" for status, n in sorted(total.statuses.items()) if status // 100 == 4)
        five = ", ".join(f"{status}: {n}" for status, n in sorted(total.statuses.items()) if status // 100 == 5)
        raised = ", ".join(f"{name}: {n}" for name, n in sorted(total.exceptions.items()))
        return [
            f"all categories: {total.cases} cases: {total.by_class(2)} 2xx, {total.by_class(3)} 3xx, "
            f"{total.by_class(4)} 4xx, {total.by_class(5)} 5xx, {sum(total.exceptions.values())} exceptions, "
            f"{total.closed} closed without an answer; {total.failures} failed a check",
            f"4xx by status: {four or 'none'}",
            f"5xx by status: {five or 'none'}; exceptions raised in the app: {raised or 'none'}",
        ]

    @staticmethod
    def _line(operation: str, row: Row, width: int) -> str:
        return (
            f"{operation:<{width}}  {row.cases:>6}  {row.kinds['positive']:>5}  {row.kinds['negative']:>5}  "
            f"{row.by_class(2):>5}  {row.by_class(4):>5}  {row.by_class(5):>4}  {sum(row.exceptions.values()):>4}  "
            f"{row.failures:>4}"
        )


TALLY = Tally()
