"""`posemetry serve` (and the benchmarks that start it) split the machine: two API processes, the rest workers."""

from __future__ import annotations

import pytest

from service.runtime import default_process_split


@pytest.mark.parametrize(
    ("cpus", "split"),
    [(1, (1, 1)), (2, (2, 1)), (3, (2, 1)), (4, (2, 2)), (16, (2, 14))],
)
def test_two_api_processes_and_the_other_cores_as_workers(cpus: int, split: tuple[int, int]) -> None:
    assert default_process_split(cpus) == split


def test_reports_name_the_split_in_words() -> None:
    from bench.server import process_counts

    assert process_counts(2, 1) == "2 API processes, 1 worker"
    assert process_counts(1, 3) == "1 API process, 3 workers"
