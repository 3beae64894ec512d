"""Prometheus text exposition read back into numbers (the load benchmark scrapes /metrics like Prometheus would)."""

from __future__ import annotations

from prometheus_client.parser import text_string_to_metric_families

# (sample name, sorted label pairs)
MetricSample = tuple[str, tuple[tuple[str, str], ...]]


def parse_metrics(text: str) -> dict[MetricSample, float]:
    """Every sample of a scrape by name and labels; histogram buckets are left out (sums and counts suffice)."""
    samples: dict[MetricSample, float] = {}
    for family in text_string_to_metric_families(text):
        for sample in family.samples:
            if sample.name.endswith("_bucket"):
                continue
            samples[(sample.name, tuple(sorted(sample.labels.items())))] = float(sample.value)
    return samples


def labelled(samples: dict[MetricSample, float], name: str) -> list[tuple[dict[str, str], float]]:
    """The samples named `name`, with their labels as a dict."""
    return [(dict(labels), value) for (sample_name, labels), value in samples.items() if sample_name == name]


def delta_by(
    start: dict[MetricSample, float], end: dict[MetricSample, float], name: str, label: str
) -> dict[str, float]:
    """How much the counter `name` grew between two scrapes, summed per value of `label`."""
    totals: dict[str, float] = {}
    for labels, value in labelled(end, name):
        before = start.get((name, tuple(sorted(labels.items()))), 0.0)
        key = labels.get(label, "")
        totals[key] = totals.get(key, 0.0) + value - before
    return totals


def jobs_by_queue(start: dict[MetricSample, float], end: dict[MetricSample, float]) -> dict[str, tuple[int, float]]:
    """Jobs finished per queue in the window, and their wall time, from the job-duration histogram's deltas."""
    counts = delta_by(start, end, "posemetry_job_duration_seconds_count", "queue")
    sums = delta_by(start, end, "posemetry_job_duration_seconds_sum", "queue")
    return {queue: (round(counts[queue]), sums.get(queue, 0.0)) for queue in counts}
