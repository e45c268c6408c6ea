"""The camera table's vehicles_seen: how many vehicles show a pixel in the instance map."""
import numpy as np

from vcfusion.render.hook import vehicles_seen


def test_vehicles_seen_counts_the_distinct_vehicles_with_a_pixel_as_np_unique_does():
    rng = np.random.default_rng(3)
    for _ in range(20):
        instances = np.full((48, 64), -1, np.int32)
        for k in rng.choice(30, size=rng.integers(0, 12), replace=False):
            y, x = rng.integers(0, 48), rng.integers(0, 64)
            instances[y:y + rng.integers(1, 10), x:x + rng.integers(1, 10)] = k
        expected = int((np.unique(instances) >= 0).sum())
        assert vehicles_seen(instances) == expected


def test_no_vehicle_in_view_is_zero_and_one_pixel_is_one():
    instances = np.full((4, 5), -1, np.int32)
    assert vehicles_seen(instances) == 0
    instances[2, 3] = 7  # a vehicle index that is not the first
    assert vehicles_seen(instances) == 1
