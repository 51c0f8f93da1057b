"""IES light profiles (`hybridgi_core/ies.py`): parsing as Cycles' util/ies.cpp does, evaluation."""

import numpy as np
import pytest

from hybridgi_core import ies

#: A type C downlight: one horizontal angle (rotationally symmetric), 0-90 degrees down.
DOWNLIGHT = """IESNA:LM-63-2002
[TEST] downlight
TILT=NONE
1 1000 2 7 1 1 2 0.1 0.1 0.0
0.5 1.0 20
0 15 30 45 60 75 90
0
3000 2500 1200 300 60 10 0
"""


def test_a_symmetric_type_c_profile_covers_every_horizontal_angle():
    p = ies.parse(DOWNLIGHT)
    assert p is not None
    np.testing.assert_allclose(np.degrees(p.h), [0.0, 360.0])
    np.testing.assert_allclose(np.degrees(p.v), [0, 15, 30, 45, 60, 75, 90], atol=1e-9)
    # Candela x multiplier 2 x ballast 0.5 x 4 pi / 177.83, as Cycles scales them.
    scale = 2.0 * 0.5 * ies.CANDELA_TO_STRENGTH
    np.testing.assert_allclose(p.table[0], np.array([3000, 2500, 1200, 300, 60, 10, 0]) * scale, rtol=1e-6)
    np.testing.assert_allclose(p.table[1], p.table[0])


def test_the_profile_is_read_from_straight_down_in_the_lamps_frame():
    p = ies.parse(DOWNLIGHT)
    scale = ies.CANDELA_TO_STRENGTH
    down = p(np.array([[0.0, 0.0, -1.0]]))
    np.testing.assert_allclose(down, 3000 * scale, rtol=1e-5)
    # 30 degrees off the axis, any azimuth; between two angles, linear.
    for azimuth in (0.0, 1.0, 2.5):
        d = np.array([[np.sin(np.radians(30)) * np.cos(azimuth), np.sin(np.radians(30)) * np.sin(azimuth),
                       -np.cos(np.radians(30))]])
        np.testing.assert_allclose(p(d), 1200 * scale, rtol=1e-4)
    d = np.array([[np.sin(np.radians(37.5)), 0.0, -np.cos(np.radians(37.5))]])
    np.testing.assert_allclose(p(d), 750 * scale, rtol=1e-4)
    # Above the horizon (beyond its last vertical angle, 90): nothing.
    assert p(np.array([[0.0, 0.0, 1.0]]))[0] == 0.0


def test_a_quadrant_of_horizontal_angles_is_mirrored_to_the_full_circle():
    text = DOWNLIGHT.replace("2 7 1 1 2", "2 2 3 1 2").replace("0 15 30 45 60 75 90\n0\n3000 2500 1200 300 60 10 0",
                                                                 "0 90\n0 45 90\n10 20\n30 40\n50 60")
    p = ies.parse(text)
    np.testing.assert_allclose(np.degrees(p.h), [0, 45, 90, 135, 180, 225, 270, 315, 360])
    # The 90-degree row, mirrored about 90 and 180.
    np.testing.assert_allclose(p.table[:, 0] / p.table[0, 0], [1, 3, 5, 3, 1, 3, 5, 3, 1])


@pytest.mark.parametrize("text", ["", "no tilt line\n1 2 3", DOWNLIGHT.replace("2 7 1 1 2", "2 7 1 3 2"),
                                  DOWNLIGHT.replace("3000 2500 1200 300 60 10 0", "3000 2500")])
def test_what_cycles_would_not_read_is_none(text):
    assert ies.parse(text) is None


def test_tilt_include_skips_its_table():
    text = DOWNLIGHT.replace("TILT=NONE\n", "TILT=INCLUDE\n1\n3\n0 45 90\n1 0.9 0.8\n")
    p = ies.parse(text)
    assert p is not None and p.table.shape == (2, 7)
