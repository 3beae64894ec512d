"""The cooldown rule: one lingering pair fires once per window; a different pair fires at once."""

from __future__ import annotations

from datetime import UTC, datetime, timedelta

from service.webhooks.cooldown import Candidate, Cooldown

T0 = datetime(2026, 1, 1, 12, tzinfo=UTC)


def at(seconds: float) -> datetime:
    return T0 + timedelta(seconds=seconds)


def pair(a: tuple[float, float], b: tuple[float, float], i: int = 0, j: int = 1) -> Candidate:
    return Candidate(i, j, a, b)


def test_a_pair_standing_still_fires_once_per_window() -> None:
    cooldown = Cooldown([], window_s=60, radius_m=1.0)
    fired_at = [t for t in range(0, 200, 2) if cooldown.admit(at(t), [pair((0.0, 5.0), (1.0, 5.0))])]
    assert fired_at == [0, 60, 120, 180]


def test_noise_in_the_positions_and_swapped_indices_are_still_the_same_pair() -> None:
    cooldown = Cooldown([], window_s=60, radius_m=1.0)
    assert cooldown.admit(at(0), [pair((0.0, 5.0), (1.0, 5.0))])
    # People are listed in another order in the next frame, and the estimates wobble by tens of centimetres.
    assert cooldown.admit(at(1), [pair((1.3, 5.2), (-0.2, 4.7), i=3, j=7)]) == []


def test_a_different_pair_elsewhere_in_the_camera_fires() -> None:
    cooldown = Cooldown([], window_s=60, radius_m=1.0)
    assert cooldown.admit(at(0), [pair((0.0, 5.0), (1.0, 5.0))])
    elsewhere = pair((8.0, 12.0), (9.0, 12.0), i=2, j=3)
    assert cooldown.admit(at(1), [pair((0.0, 5.0), (1.0, 5.0)), elsewhere]) == [elsewhere]


def test_one_person_of_the_pair_replaced_by_someone_else_fires() -> None:
    cooldown = Cooldown([], window_s=60, radius_m=1.0)
    assert cooldown.admit(at(0), [pair((0.0, 5.0), (1.0, 5.0))])
    newcomer = pair((0.0, 5.0), (0.0, 6.5))  # the first stays, the other one is 1.8 m from the old partner
    assert cooldown.admit(at(5), [newcomer]) == [newcomer]


def test_a_pair_walking_together_stays_one_pair() -> None:
    cooldown = Cooldown([], window_s=60, radius_m=1.0)
    fired = 0
    for step in range(30):  # 0.5 m per second for 30 s: 15 m from where it was alerted
        y = 5.0 + 0.5 * step
        fired += len(cooldown.admit(at(step), [pair((0.0, y), (1.0, y))]))
    assert fired == 1


def test_pairs_of_one_frame_never_silence_each_other() -> None:
    cooldown = Cooldown([], window_s=60, radius_m=1.0)
    huddle = [
        pair((0.0, 5.0), (0.6, 5.0), 0, 1),
        pair((0.0, 5.0), (0.3, 5.5), 0, 2),
        pair((0.6, 5.0), (0.3, 5.5), 1, 2),
    ]
    assert cooldown.admit(at(0), huddle) == huddle
    assert cooldown.admit(at(1), huddle) == []


def test_window_zero_fires_every_frame_and_late_frames_are_judged_by_their_time() -> None:
    every = Cooldown([], window_s=0, radius_m=1.0)
    assert all(every.admit(at(t), [pair((0.0, 5.0), (1.0, 5.0))]) for t in range(5))
    cooldown = Cooldown([], window_s=60, radius_m=1.0)
    assert cooldown.admit(at(100), [pair((0.0, 5.0), (1.0, 5.0))])
    assert cooldown.admit(at(95), [pair((0.0, 5.0), (1.0, 5.0))]) == []  # an older frame measured late
    assert cooldown.admit(at(20), [pair((0.0, 5.0), (1.0, 5.0))])  # 80 s before the alert: its own event
