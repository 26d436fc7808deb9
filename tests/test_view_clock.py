"""sim_stub.view_clock: how long a person had been inside the camera's horizontal view."""

from __future__ import annotations

import math

import numpy as np
import pytest

from sim_stub.view_clock import ViewClock

R = np.array([0.25])


def test_a_person_inside_the_wedge_any_part_of_them_counts():
    clock = ViewClock((0.1, 0.0), 87.0, 4.0, 1)

    def at(x: float, y: float) -> bool:
        return bool(clock.in_view((0.0, 0.0, 0.0), np.array([[x, y]]), R)[0])

    assert at(2.0, 0.0) and not at(-1.0, 0.0)
    # 50 deg off the axis: the centre is outside 43.5 deg, but the disc reaches into the wedge
    # from near (its angular half-width is larger there) and not from far
    near, far = 0.6, 3.0
    assert at(0.1 + near * math.cos(math.radians(50)), near * math.sin(math.radians(50)))
    assert not at(0.1 + far * math.cos(math.radians(50)), far * math.sin(math.radians(50)))
    assert not at(4.5, 0.0)  # beyond the perception's range
    # the robot's pose moves the wedge: turned left 90 deg, a person at +y is ahead
    assert clock.in_view((0.0, 0.0, math.pi / 2), np.array([[0.0, 2.0]]), R)[0]


def test_the_clock_counts_from_the_last_entry_and_is_zero_outside():
    clock = ViewClock((0.0, 0.0), 87.0, 4.0, 2)
    inside, outside = np.array([[2.0, 0.0]]), np.array([[-2.0, 0.0]])
    for t, p in ((0.0, outside), (1.0, inside), (2.0, inside), (3.0, outside), (4.0, inside)):
        clock.update(t, (0.0, 0.0, 0.0), np.concatenate([p, inside]), np.repeat(R, 2))
        if t == 2.0:
            assert clock.seen_for(0, t) == pytest.approx(1.0)
        if t == 3.0:
            assert clock.seen_for(0, t) == 0.0
    assert clock.seen_for(0, 4.5) == pytest.approx(0.5)  # entered again at 4 s
    assert clock.seen_for(1, 4.5) == pytest.approx(4.5)  # in view all along
