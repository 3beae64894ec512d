"""Geometry benchmark: Monte Carlo accuracy of calibrate() on simulated scenes (paper Sect. 4.1), and its speed.

Only the public API (calibrate, CalibrationError) and the simulator are used,
so the numbers describe what a caller gets. Methods (named calibrate()
configurations) are in bench.methods, metrics in bench.metrics, the camera
model's coverage experiment in bench.coverage.

Every trial seeds its scene from (seed, experiment name, trial index) alone,
so results do not depend on --workers or --only, and all settings and methods
of one experiment see the same random cameras and people: their differences
are paired comparisons, not luck of the draw.
"""

from __future__ import annotations

import math
import os
import platform
import time
import warnings
import zlib
from collections.abc import Callable, Mapping, Sequence
from concurrent.futures import Executor, ProcessPoolExecutor
from dataclasses import dataclass, field, replace
from datetime import UTC, datetime
from typing import Any, Final

import numpy as np
from numpy.typing import NDArray

from bench.simulate import SceneConfig, draw_scene
from service.geometry import CalibrationError, calibrate

from . import paper
from .coverage import MAX_TRIALS, realistic_tables
from .methods import METHODS, Setting, problem_and_options, run_method, without_outliers
from .metrics import EXTRA_KEYS, METRIC_KEYS, TrialResult
from .report import ReportTable, fmt, fmt_pair, yes_no

FloatArray = NDArray[np.float64]

# The method whose rows the pass/fail targets of the outlier and distance experiments judge.
TARGET_METHOD: Final = "default"

LABELS: Final = {
    "fx_pct": "fx %",
    "fy_pct": "fy %",
    "normal_deg": "N deg",
    "rho_pct": "rho %",
    "points_pct": "X %",
    "dist_pct": "dist %",
    "dist_m": "dist m",
    "fail_pct": "fail %",
}

# The distortion experiment's k search costs ~0.1 s a scene: it runs at most this many trials per setting.
DISTORTION_MAX_TRIALS: Final = 300
EXPERIMENTS: Final = (
    "noise-free",
    "table1",
    "table2",
    "table3",
    "outliers",
    "distance",
    "surveillance",
    "distortion",
    "realistic",
    "timing",
)

NOISE_FREE_RESOLUTIONS: Final = ((640, 480), (1280, 720), (1920, 1080))
NOISE_FREE_FOVS_DEG: Final = (45.0, 60.0, 90.0, 120.0)
NOISE_FREE_TOLERANCE: Final = 1e-6  # % for relative errors, degrees for the normal
OUTLIER_RATIO_TARGET: Final = 1.5
DISTANCE_TARGETS_PCT: Final = {20: 4.0, 100: 2.0}
TIMING_CASES: Final = (
    ("linear", 10),
    ("linear", 100),
    ("linear", 1000),
    ("robust", 100),
    ("robust", 1000),
    ("default", 100),
    ("default", 1000),
)
TIMING_TARGETS_MS: Final = {("linear", 1000): 2.0, ("robust", 1000): 50.0}


# --- trials --------------------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class Trial:
    setting: Setting
    methods: tuple[tuple[str, Mapping[str, Any]], ...]
    entropy: int
    key: tuple[int, ...]


def run_trial(trial: Trial) -> tuple[TrialResult, ...]:
    """Draw the trial's scene and run every method on it (top level, so worker processes can unpickle it)."""
    scene_seed = np.random.SeedSequence(trial.entropy, spawn_key=(*trial.key, 0))
    calibrate_seed = int(np.random.SeedSequence(trial.entropy, spawn_key=(*trial.key, 1)).generate_state(1)[0])
    scene = draw_scene(trial.setting.config, np.random.default_rng(scene_seed))
    if trial.setting.drop_outliers:
        scene = without_outliers(scene)
    with warnings.catch_warnings():
        # Degenerate noisy draws make numpy warn; the failure rate and errors already account for them.
        warnings.simplefilter("ignore", RuntimeWarning)
        return tuple(run_method(scene, trial.setting, kwargs, calibrate_seed) for _, kwargs in trial.methods)


@dataclass(frozen=True)
class Summary:
    """Statistics of one (setting, method) over its trials; errors over successful trials only, as in the paper."""

    trials: int
    failures: int
    unexpected: int
    first_error: str
    mean: Mapping[str, float]
    median: Mapping[str, float]
    max: Mapping[str, float]

    @property
    def fail_pct(self) -> float:
        return 100.0 * self.failures / self.trials if self.trials else math.nan


def summarise(results: Sequence[TrialResult]) -> Summary:
    ok = [r for r in results if not r.failed]
    mean, median, largest = {}, {}, {}
    for key in (*METRIC_KEYS, *EXTRA_KEYS):
        values = np.array([r.metrics[key] for r in ok], dtype=np.float64)
        values = values[np.isfinite(values)]
        mean[key] = float(values.mean()) if values.size else math.nan
        median[key] = float(np.median(values)) if values.size else math.nan
        largest[key] = float(values.max()) if values.size else math.nan
    unexpected = [r for r in results if r.unexpected]
    first = (unexpected or [r for r in results if r.failed] or [TrialResult()])[0].error
    return Summary(len(results), len(results) - len(ok), len(unexpected), first, mean, median, largest)


# --- running -----------------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class BenchmarkOptions:
    trials: int = 1000
    seed: int = 0
    workers: int = 2
    only: tuple[str, ...] = EXPERIMENTS
    repeats: int = 50  # timing repetitions per case


@dataclass
class BenchmarkReport:
    header: list[str]
    tables: list[ReportTable]
    # One line per (experiment, setting, method) whose trials raised something other than CalibrationError.
    unexpected_errors: list[str] = field(default_factory=list)


Results = dict[tuple[str, str], Summary]


@dataclass
class _Context:
    options: BenchmarkOptions
    executor: Executor | None
    progress: Callable[[str], None]
    unexpected_errors: list[str] = field(default_factory=list)

    def run(
        self, experiment: str, settings: Sequence[Setting], methods: Sequence[str], max_trials: int | None = None
    ) -> Results:
        """Summaries keyed by (setting label, method name)."""
        items = tuple((m, dict(METHODS[m])) for m in methods)
        salt = zlib.crc32(experiment.encode())
        count = self.options.trials if max_trials is None else min(self.options.trials, max_trials)
        trials = [Trial(s, items, self.options.seed, (salt, i)) for s in settings for i in range(count)]
        start = time.perf_counter()
        if self.executor is None:
            outputs = list(map(run_trial, trials))
        else:
            chunk = max(1, len(trials) // (8 * max(self.options.workers, 1)))
            outputs = list(self.executor.map(run_trial, trials, chunksize=chunk))
        results: Results = {}
        for k, setting in enumerate(settings):
            block = outputs[k * count : (k + 1) * count]
            for j, method in enumerate(methods):
                summary = summarise([out[j] for out in block])
                results[setting.label, method] = summary
                if summary.unexpected:
                    self.unexpected_errors.append(
                        f"{experiment} / {setting.label} / {method}: {summary.unexpected} trial(s) raised; "
                        f"first: {summary.first_error}"
                    )
        self.progress(
            f"{experiment}: {len(trials)} scenes x {len(methods)} method(s) in {time.perf_counter() - start:.1f} s"
        )
        return results


def parse_only(text: str | None) -> tuple[str, ...]:
    """Experiment names from a comma-separated list, in canonical order; every experiment when empty."""
    if not text:
        return EXPERIMENTS
    names = {part.strip() for part in text.split(",") if part.strip()}
    unknown = sorted(names - set(EXPERIMENTS))
    if unknown:
        raise ValueError(f"unknown experiment(s): {', '.join(unknown)}; choose from {', '.join(EXPERIMENTS)}")
    return tuple(name for name in EXPERIMENTS if name in names)


def machine_header(options: BenchmarkOptions) -> list[str]:
    return [
        f"date: {datetime.now(UTC):%Y-%m-%d %H:%M} UTC",
        f"machine: {platform.system()} {platform.machine()}, {os.cpu_count()} CPUs; "
        f"Python {platform.python_version()}, numpy {np.__version__}",
        f"trials per setting: {options.trials}; seed {options.seed}; workers {options.workers}; "
        f"timing repetitions {options.repeats}",
    ]


def run_benchmark(options: BenchmarkOptions, progress: Callable[[str], None] | None = None) -> BenchmarkReport:
    unknown = set(options.only) - set(EXPERIMENTS)
    if unknown:
        raise ValueError(f"unknown experiment(s): {sorted(unknown)}")
    if options.trials < 1 or options.repeats < 1 or options.workers < 1:
        raise ValueError("trials, repeats and workers must be at least 1")
    report = BenchmarkReport(machine_header(options), [])
    accuracy = [name for name in options.only if name != "timing"]
    executor = ProcessPoolExecutor(options.workers) if options.workers > 1 and accuracy else None
    ctx = _Context(options, executor, progress or (lambda _: None), report.unexpected_errors)
    try:
        for name in options.only:
            report.tables.extend(_EXPERIMENT_FUNCTIONS[name](ctx))
    finally:
        if executor is not None:
            executor.shutdown(cancel_futures=True)
    return report


# --- experiments -------------------------------------------------------------------------------------------------


def _noise_free(ctx: _Context) -> list[ReportTable]:
    settings = [
        Setting(
            f"{w}x{h}, FOV {fov:g}",
            SceneConfig.paper(image_size=(w, h), vfov_deg=(fov, fov), n_people=3, noise_px=0.0, height_std_m=0.0),
            # The people are exactly the prior's height: with a spread allowed for, three noise-free people
            # would not pin f (each person's own height is then unknown).
            problem={"height_std_m": 1e-6},
        )
        for (w, h) in NOISE_FREE_RESOLUTIONS
        for fov in NOISE_FREE_FOVS_DEG
    ]
    methods = ("linear", "default")
    results = ctx.run("noise-free", settings, methods)
    table = ReportTable(
        "Noise-free, 3 people (minimal), fx = (W/H) fy: largest error over trials",
        ["setting", "method", *(f"max {LABELS[k]}" for k in METRIC_KEYS), "fail %", f"< {NOISE_FREE_TOLERANCE:g}"],
    )
    for setting in settings:
        for method in methods:
            s = results[setting.label, method]
            ok = s.failures == 0 and all(s.max[k] < NOISE_FREE_TOLERANCE for k in METRIC_KEYS if k != "dist_m")
            table.add_row(setting.label, method, *(fmt(s.max[k]) for k in METRIC_KEYS), fmt(s.fail_pct), yes_no(ok))
        table.end_section()
    table.notes.append(
        f"Target: every relative error below {NOISE_FREE_TOLERANCE:g} % and the normal below "
        f"{NOISE_FREE_TOLERANCE:g} deg, with no failures ({ctx.options.trials} trials per setting; dist m not judged)."
    )
    return [table]


def _paper_table(
    ctx: _Context, name: str, title: str, settings: Sequence[Setting], rows: paper.PaperRows
) -> list[ReportTable]:
    methods = ("as-printed", "linear", "default")
    results = ctx.run(name, settings, methods)
    table = ReportTable(title, ["error", "row", *(s.label for s in settings)])
    passed = dict.fromkeys(methods, 0)
    judged = 0
    for key in (*METRIC_KEYS, "fail_pct"):
        for method in methods:
            cells = []
            for s in settings:
                summary = results[s.label, method]
                cells.append(
                    fmt(summary.fail_pct) if key == "fail_pct" else fmt_pair(summary.mean[key], summary.median[key])
                )
            table.add_row(LABELS[key] if method == methods[0] else "", method, *cells)
        if key not in rows["Ours"]:
            table.end_section()
            continue
        for source in ("Ours", "Baseline"):
            table.add_row("", f"paper {source}", *(fmt(v) for v in rows[source][key]))
        judged += len(settings)
        for method in methods:
            checks = []
            for s, published in zip(settings, rows["Ours"][key], strict=True):
                summary = results[s.label, method]
                ours = summary.fail_pct if key == "fail_pct" else summary.mean[key]
                ok = math.isfinite(ours) and ours <= 0.5 * published
                passed[method] += ok
                checks.append(yes_no(ok))
            table.add_row("", f"{method} <= Ours/2", *checks)
        table.end_section()
    table.notes.append(
        f"Cells: mean (median) over successful trials, {ctx.options.trials} trials per column "
        f"(paper: mean of {paper.PAPER_TRIALS}). '<= Ours/2': our mean is at most half of the paper's Ours."
    )
    table.notes.append(
        "Cells at most half of paper Ours: " + "; ".join(f"{m} {passed[m]}/{judged}" for m in methods) + "."
    )
    return [table]


def _table1(ctx: _Context) -> list[ReportTable]:
    settings = [
        Setting(f"{noise:g} px", SceneConfig.paper(noise_px=noise, height_std_m=0.0, n_people=20))
        for noise in paper.TABLE1_NOISE_PX
    ]
    title = "Table 1: error vs keypoint noise (1920x1080, FOV 90, fx = (W/H) fy, 20 people, height std 0)"
    return _paper_table(ctx, "table1", title, settings, paper.TABLE1)


def _table2(ctx: _Context) -> list[ReportTable]:
    settings = [
        Setting(f"{std:g} m", SceneConfig.paper(noise_px=0.5, height_std_m=std, height_range_m=(1.5, 1.9)))
        for std in paper.TABLE2_HEIGHT_STD_M
    ]
    title = "Table 2: error vs height std (noise 0.5 px, heights truncated to [1.5, 1.9] m, 20 people)"
    return _paper_table(ctx, "table2", title, settings, paper.TABLE2)


def _table3(ctx: _Context) -> list[ReportTable]:
    settings = [
        Setting(f"{n} people", SceneConfig.paper(noise_px=0.5, height_std_m=0.1, n_people=n))
        for n in paper.TABLE3_PEOPLE
    ]
    title = "Table 3: error vs number of people (noise 0.5 px, height std 0.1 m)"
    return _paper_table(ctx, "table3", title, settings, paper.TABLE3)


def _outliers(ctx: _Context) -> list[ReportTable]:
    settings: list[Setting] = []
    for n in (20, 100):
        dirty = SceneConfig.paper(noise_px=0.5, height_std_m=0.1, n_people=n, outlier_fraction=0.3)
        settings += [
            Setting(f"{n} outliers", dirty),
            Setting(f"{n} clean", replace(dirty, outlier_fraction=0.0)),
            Setting(f"{n} oracle", dirty, drop_outliers=True),
        ]
    methods = ("default", "linear")
    results = ctx.run("outliers", settings, methods)
    table = ReportTable(
        "Outliers: 30% of people sitting, bending, on stairs or misdetected (noise 0.5 px, height std 0.1 m)",
        [
            "people",
            "method",
            "fx % outliers",
            "fx % clean",
            "ratio",
            f"<= {OUTLIER_RATIO_TARGET:g}",
            "fx % oracle",
            "fail % outliers",
            "fail % clean",
            "inliers kept %",
            "outliers kept %",
        ],
    )
    for n in (20, 100):
        for method in methods:
            dirty, clean, oracle = (results[f"{n} {kind}", method] for kind in ("outliers", "clean", "oracle"))
            ratio = dirty.mean["fx_pct"] / clean.mean["fx_pct"] if clean.mean["fx_pct"] > 0 else math.nan
            target = yes_no(math.isfinite(ratio) and ratio <= OUTLIER_RATIO_TARGET) if method == TARGET_METHOD else "-"
            table.add_row(
                str(n),
                method,
                fmt_pair(dirty.mean["fx_pct"], dirty.median["fx_pct"]),
                fmt_pair(clean.mean["fx_pct"], clean.median["fx_pct"]),
                fmt(ratio),
                target,
                fmt_pair(oracle.mean["fx_pct"], oracle.median["fx_pct"]),
                fmt(dirty.fail_pct),
                fmt(clean.fail_pct),
                fmt(dirty.mean["inliers_placed_pct"]),
                fmt(dirty.mean["outliers_placed_pct"]),
            )
        table.end_section()
    table.notes.append(
        "fx error mean (median) over successful trials. clean: the same cameras and people with no outliers "
        "(outlier_fraction 0); oracle: the outlier scenes with the outliers removed before calibrating. "
        f"ratio = mean outliers / mean clean; the target applies to '{TARGET_METHOD}'. "
        "kept %: share of true inliers / outliers the calibration placed."
    )
    return [table]


def _distance(ctx: _Context) -> list[ReportTable]:
    settings = [
        Setting(f"{n} people", SceneConfig.paper(noise_px=0.5, height_std_m=0.1, n_people=n))
        for n in DISTANCE_TARGETS_PCT
    ]
    methods = ("default", "linear")
    results = ctx.run("distance", settings, methods)
    table = ReportTable(
        "Pairwise ground distance error vs number of people (noise 0.5 px, height std 0.1 m, fx = (W/H) fy)",
        ["people", "method", "dist %", "dist m", "fail %", "target dist %", "pass"],
    )
    for setting, target in zip(settings, DISTANCE_TARGETS_PCT.values(), strict=True):
        for method in methods:
            s = results[setting.label, method]
            ok = yes_no(s.mean["dist_pct"] <= target) if method == TARGET_METHOD else "-"
            table.add_row(
                setting.label,
                method,
                fmt_pair(s.mean["dist_pct"], s.median["dist_pct"]),
                fmt_pair(s.mean["dist_m"], s.median["dist_m"]),
                fmt(s.fail_pct),
                f"<= {target:g}",
                ok,
            )
        table.end_section()
    table.notes.append(
        "Mean (median) over successful trials of each trial's mean over all pairs of placed people. "
        f"The target applies to the mean of '{TARGET_METHOD}'."
    )
    return [table]


def _surveillance(ctx: _Context) -> list[ReportTable]:
    settings = [Setting(f"{n} people", SceneConfig.surveillance(n_people=n), equal_focal=True) for n in (20, 100)]
    methods = ("default",)
    results = ctx.run("surveillance", settings, methods)
    table = ReportTable(
        "Surveillance preset: square pixels (equal_focal), FOV 30-70, 3-10 m up, noise 1.5 px, height std 0.07 m",
        ["people", "method", *(LABELS[k] for k in METRIC_KEYS), "fail %"],
    )
    for setting in settings:
        for method in methods:
            s = results[setting.label, method]
            table.add_row(
                setting.label, method, *(fmt_pair(s.mean[k], s.median[k]) for k in METRIC_KEYS), fmt(s.fail_pct)
            )
    table.notes.append("Mean (median) over successful trials.")
    return [table]


def _distortion(ctx: _Context) -> list[ReportTable]:
    """Appendix C's question on a square-pixel camera: does modelling lens distortion help, and under noise?"""
    settings = [
        Setting(
            f"k1 {k1:+g}, {noise:g} px",
            SceneConfig.surveillance(n_people=50, distortion_k=(k1, 0.0), noise_px=noise, height_std_m=0.07),
            equal_focal=True,
        )
        for k1 in (0.0, 0.05, -0.05, -0.15)
        for noise in (0.0, 2.0)
    ]
    methods = ("no-lens", "default")
    results = ctx.run("distortion", settings, methods, max_trials=DISTORTION_MAX_TRIALS)
    keys = ("fx_pct", "normal_deg", "rho_pct", "dist_pct")
    table = ReportTable(
        "Lens distortion: OpenCV polynomial k1 (focal-normalised radius) on the surveillance preset, 50 people",
        ["setting", "method", *(LABELS[k] for k in keys), "fail %"],
    )
    for setting in settings:
        for method in methods:
            s = results[setting.label, method]
            table.add_row(setting.label, method, *(fmt_pair(s.mean[k], s.median[k]) for k in keys), fmt(s.fail_pct))
        table.end_section()
    table.notes.append(
        f"{min(ctx.options.trials, DISTORTION_MAX_TRIALS)} trials per setting (the k search is the slowest step). "
        "Mean (median). 'default' estimates a one-parameter division model (a different model from the "
        "simulated polynomial lens), kept at k = 0 unless significant and material; 'no-lens' = "
        "SolveOptions(distortion=False)."
    )
    return [table]


def _timing(ctx: _Context) -> list[ReportTable]:
    """Timed in this process, one call at a time: what a single request costs, not throughput."""
    table = ReportTable(
        "Timing: one calibrate() call (noise 0.5 px, height std 0.1 m, fx = (W/H) fy)",
        ["method", "people", "median ms", "p90 ms", "target ms", "pass"],
    )
    salt = zlib.crc32(b"timing")
    start = time.perf_counter()
    for method, n in TIMING_CASES:
        config = SceneConfig.paper(noise_px=0.5, height_std_m=0.1, n_people=n)
        scene = draw_scene(config, np.random.default_rng(np.random.SeedSequence(ctx.options.seed, spawn_key=(salt, n))))
        problem, solve_options = problem_and_options(scene.image_size, config.height_mean_m, False, METHODS[method], 0)
        target = TIMING_TARGETS_MS.get((method, n))
        target_cell = f"<= {target:g}" if target is not None else "-"
        try:
            times_ms = _time_calls(
                lambda p=problem, o=solve_options, s=scene: calibrate(s.tops_px, s.bottoms_px, p, o),
                ctx.options.repeats,
            )
        except CalibrationError as exc:
            table.add_row(method, str(n), "failed", "-", target_cell, yes_no(False if target else None))
            table.notes.append(f"{method} with {n} people: {exc}")
            continue
        median, p90 = float(np.median(times_ms)), float(np.percentile(times_ms, 90))
        table.add_row(
            method, str(n), fmt(median), fmt(p90), target_cell, yes_no(median <= target if target is not None else None)
        )
    table.notes.append(
        f"{ctx.options.repeats} timed calls per row after one warm-up call; time.perf_counter, single process. "
        "Targets judge the median."
    )
    ctx.progress(f"timing: {len(TIMING_CASES)} cases in {time.perf_counter() - start:.1f} s")
    return [table]


def _time_calls(call: Callable[[], object], repeats: int) -> FloatArray:
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        call()
        times = np.empty(repeats)
        for i in range(repeats):
            t0 = time.perf_counter()
            call()
            times[i] = time.perf_counter() - t0
    return 1e3 * times


def _realistic(ctx: _Context) -> list[ReportTable]:
    """Coverage and accuracy on real cameras' mismatches (bench.coverage), before and after the camera model."""
    start = time.perf_counter()
    mapper = map if ctx.executor is None else (lambda f, items: ctx.executor.map(f, items, chunksize=4))
    tables = realistic_tables(ctx.options.trials, ctx.options.seed, mapper)
    ctx.progress(f"realistic: {min(ctx.options.trials, MAX_TRIALS)} scenes in {time.perf_counter() - start:.1f} s")
    return tables


_EXPERIMENT_FUNCTIONS: Final[dict[str, Callable[[_Context], list[ReportTable]]]] = {
    "noise-free": _noise_free,
    "table1": _table1,
    "table2": _table2,
    "table3": _table3,
    "outliers": _outliers,
    "distance": _distance,
    "surveillance": _surveillance,
    "distortion": _distortion,
    "realistic": _realistic,
    "timing": _timing,
}
