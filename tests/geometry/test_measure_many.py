"""Measuring many frames in one pass (measure_many) gives each frame what measuring it alone gives.

The per-frame reference is `measure`, whose (N, N) matrices come from a one-frame pass: what this checks is that a
chunk keeps its frames apart (pairs only within a frame, each person's own priors and noise, frames of 0 or 1
person, unplaceable people) under calibrations with and without an uncertainty and with a lens.
"""

from __future__ import annotations

import itertools
from dataclasses import replace

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from service.geometry import Calibration, OpenCVLens, Uncertainty, measure, measure_many
from tests.render.scenes import calibration_of, tilted_scene

# 1-sigma of the canonical parameters (fx, fy, t1, t2, rho, cx, cy, k): a camera solved from a modest crowd.
_SIGMAS = np.array([25.0, 25.0, 0.01, 0.015, 0.08, 6.0, 6.0, 0.01])


def _uncertainty(rng: np.random.Generator, size: int) -> Uncertainty:
    """A covariance over the first `size` canonical parameters with random correlations."""
    a = rng.normal(size=(size, size))
    corr = a @ a.T + size * np.eye(size)
    d = 1.0 / np.sqrt(np.diag(corr))
    cov = (corr * d[:, None] * d[None, :]) * _SIGMAS[:size, None] * _SIGMAS[None, :size]
    return Uncertainty(
        fx_px=25.0, fy_px=25.0, normal_deg=1.0, rho_m=0.08, covariance=cov, noise_px=1.5, noise_per_length=0.01
    )


def _calibrations() -> dict[str, Calibration]:
    base = calibration_of(tilted_scene(n_people=4), height_m=1.7)
    rng = np.random.default_rng(5)
    return {
        "no uncertainty": base,
        "eight parameters": replace(base, uncertainty=_uncertainty(rng, 8), distortion_k=-0.03),
        "five parameters": replace(base, uncertainty=_uncertainty(rng, 5)),
        "opencv lens": replace(base, uncertainty=_uncertainty(rng, 8), lens=OpenCVLens(-0.1, 0.02)),
    }


CALIBRATIONS = _calibrations()


def _chunk(seed: int, sizes: list[int]) -> dict[str, np.ndarray]:
    """People of frames of `sizes`: standing, seated, partly seen, placed from a box, some unplaceable."""
    rng = np.random.default_rng(seed)
    n = sum(sizes)
    bottoms = np.column_stack((rng.uniform(50, 1230, n), rng.uniform(380, 710, n)))
    tops = bottoms - np.column_stack((rng.normal(0, 4, n), rng.uniform(40, 200, n)))
    kind = rng.integers(0, 6, n)
    bottoms[kind == 1] = np.nan  # shoulders only
    tops[kind == 2] = bottoms[kind == 2] = np.nan  # not seen at all
    tops[kind == 3, 1] = 5.0  # shoulders at the top edge: far away, or a ray that misses the raised plane
    bottoms[kind == 3] = np.nan
    return {
        "tops": tops,
        "bottoms": bottoms,
        "height_scale": np.where(rng.random(n) < 0.3, 0.78, 1.0),
        "height_std_m": rng.choice([0.07, 0.12, 0.3], n),
        "contact_std_fraction": np.where(rng.random(n) < 0.3, 0.06, 0.0),
    }


def _assert_close(a: np.ndarray, b: np.ndarray) -> None:
    np.testing.assert_array_equal(np.isnan(a), np.isnan(b))
    np.testing.assert_allclose(a, b, rtol=1e-12, atol=0.0, equal_nan=True)


@settings(max_examples=60, deadline=None)
@given(
    st.sampled_from(sorted(CALIBRATIONS)),
    st.lists(st.integers(0, 7), min_size=1, max_size=6),
    st.integers(0, 2**31),
    st.sampled_from([None, 0.0, 2.5]),
)
def test_a_chunk_measures_each_frame_as_measuring_it_alone(
    calibration: str, sizes: list[int], seed: int, noise_px: float | None
) -> None:
    cal = CALIBRATIONS[calibration]
    people = _chunk(seed, sizes)
    chunk = measure_many(cal, people.pop("tops"), people.pop("bottoms"), sizes, noise_px, **people)
    people = _chunk(seed, sizes)
    starts = np.concatenate(([0], np.cumsum(sizes)))
    for f, (n0, n1) in enumerate(itertools.pairwise(starts)):
        alone = measure(cal, noise_px=noise_px, **{name: values[n0:n1] for name, values in people.items()})
        _assert_close(chunk.points_bottom[n0:n1], alone.points_bottom)
        np.testing.assert_array_equal(chunk.from_ankles[n0:n1], alone.from_ankles)
        pairs = slice(chunk.pair_starts[f], chunk.pair_starts[f + 1])
        first, second = chunk.first[pairs] - n0, chunk.second[pairs] - n0
        assert np.all((first >= 0) & (first < second) & (second < n1 - n0))  # within the frame, i < j
        assert len(first) == (n1 - n0) * (n1 - n0 - 1) // 2
        _assert_close(chunk.distances_m[pairs], alone.distances_m[first, second])
        _assert_close(chunk.distance_std_m[pairs], alone.distance_std_m[first, second])
    assert chunk.pair_starts[-1] == len(chunk.first) == len(chunk.distances_m)


def test_the_chunk_test_sees_placeable_unplaceable_and_uncertain_people() -> None:
    """The random chunks exercise what they claim: people placed from ankles and shoulders, unplaced ones, and
    sigmas that differ between calibrations."""
    people = _chunk(1, [20, 20])
    with_unc = measure_many(CALIBRATIONS["eight parameters"], people["tops"], people["bottoms"], [20, 20])
    without = measure_many(CALIBRATIONS["no uncertainty"], people["tops"], people["bottoms"], [20, 20])
    placed = np.all(np.isfinite(with_unc.points_bottom), axis=1)
    assert with_unc.from_ankles.any() and (placed & ~with_unc.from_ankles).any() and (~placed).any()
    known = np.isfinite(with_unc.distance_std_m) & np.isfinite(without.distance_std_m)
    assert known.sum() > 100 and np.all(with_unc.distance_std_m[known] > without.distance_std_m[known])


def test_counts_must_add_up_to_the_people() -> None:
    cal = CALIBRATIONS["no uncertainty"]
    tops, bottoms = np.full((3, 2), 500.0), np.full((3, 2), 600.0)
    with pytest.raises(ValueError, match="frames of"):
        measure_many(cal, tops, bottoms, [1, 1])
    empty = measure_many(cal, np.zeros((0, 2)), np.zeros((0, 2)), [0, 0])
    assert (
        empty.points_bottom.shape == (0, 3) and len(empty.distances_m) == 0 and empty.pair_starts.tolist() == [0, 0, 0]
    )
