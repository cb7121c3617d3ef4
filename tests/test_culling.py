"""A prior's culling (``localization._seen_from``): what a camera in the prior's ball could see at the size
of the image's segments, however tight the prior."""

import numpy as np

from linereg.localization import _seen_from
from linereg.map.linemap import LineMap


def test_a_tight_prior_keeps_far_long_lines_and_drops_far_short_ones(camera):
    segments = np.array(
        [
            [30.0, -10.0, 0.0, 30.0, 10.0, 0.0],  # a 20 m kerb 30 m away: 530 px at f 800
            [30.0, 0.0, 1.0, 30.0, 0.5, 1.0],  # a 0.5 m sign 30 m away: 13 px
            [1.0, 0.0, 0.0, 1.0, 0.2, 0.0],  # a 0.2 m edge 1 m away: 160 px
            [300.0, 0.0, 0.0, 300.0, 0.5, 0.0],  # 0.5 m, 300 m away
        ]
    )
    line_map = LineMap.from_segments(segments)
    lines2d = np.array([[0.0, 0.0, 40.0, 0.0], [10.0, 10.0, 10.0, 200.0]])  # the shortest: 40 px
    kept = _seen_from(line_map, np.zeros(3), 0.5, camera, lines2d)
    assert kept.tolist() == [0, 2]
    # a wide prior reaches the sign: 0.5 m projects to 40 px from 10 m
    assert _seen_from(line_map, np.zeros(3), 20.5, camera, lines2d).tolist() == [0, 1, 2]
