"""vcfusion.bench's ratios (the sections themselves are run by `vcfusion bench`)."""

import pytest

from vcfusion.bench import least_time_ratio


def test_the_least_time_ratio_takes_each_trips_least_disturbed_run():
    loop = {0: [4.0, 3.0, 5.0], 1: [8.0, 9.0, 6.0]}
    sumo = {0: [1.5, 1.0, 1.2], 1: [2.0, 2.5, 3.0]}
    assert least_time_ratio(loop, sumo) == pytest.approx((3.0 + 6.0) / (1.0 + 2.0))
    # a disturbed repeat (other work on the machine) leaves it as it is
    loop[0].append(40.0)
    assert least_time_ratio(loop, sumo) == pytest.approx(3.0)
    with pytest.raises(ValueError, match="same trips"):
        least_time_ratio(loop, {0: [1.0]})
