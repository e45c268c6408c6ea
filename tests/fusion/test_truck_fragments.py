"""The depth step's truck fragments: two truck boxes on one depth segment become its union."""
import numpy as np
from scipy import ndimage

from vcfusion.fusion.box_refine import ObjectSegments, core_segment, join_truck_fragments

Y_LO = 10  # the segments' first image row


def _segments(rects, shape=(120, 320)):
    """Segments of the given image rectangles (x1, y1, x2, y2 pixel indices, inclusive), one label each."""
    labels = np.zeros(shape, int)
    for k, (x1, y1, x2, y2) in enumerate(rects, start=1):
        labels[y1 - Y_LO:y2 - Y_LO + 1, x1:x2 + 1] = k
    z = np.where(labels > 0, 40.0, 0.0)
    return ObjectSegments(z=z, valid=labels > 0, obj=labels > 0, height=np.where(labels > 0, 1.5, 0.0),
                          labels=labels, areas=np.bincount(labels.ravel()), regions=ndimage.find_objects(labels),
                          y_lo=Y_LO)


TRUCK = (100, 50, 160, 80)  # a truck's segment, pixels 100-160 x 50-80
FRONT = np.array([99.5, 49.5, 135.5, 80.5])  # the detector's box on its front part
BACK = np.array([124.5, 49.5, 160.5, 70.5])  # and on its back part (curved seed 5020 at 57.7 s)


def test_two_boxes_on_one_trucks_segment_become_their_union_on_the_best_scored():
    segments = _segments([TRUCK])
    assert core_segment(FRONT, segments) == 1 and core_segment(BACK, segments) == 1
    boxes = np.stack([BACK, FRONT])
    joined, keep = join_truck_fragments(boxes, np.array([0.4, 0.8]), np.array([True, True]), segments)
    assert keep.tolist() == [False, True]
    np.testing.assert_allclose(joined[1], [99.5, 49.5, 160.5, 80.5])
    np.testing.assert_allclose(boxes, np.stack([BACK, FRONT]))  # the input is left as it was


def test_boxes_of_other_segments_classes_or_columns_stay_apart():
    segments = _segments([TRUCK, (200, 50, 260, 80)])  # a second truck beside it, its own segment
    other = np.array([199.5, 49.5, 230.5, 80.5])
    joined, keep = join_truck_fragments(np.stack([FRONT, other]), np.array([0.8, 0.7]), np.array([True, True]),
                                        segments)
    assert keep.all()
    np.testing.assert_allclose(joined, np.stack([FRONT, other]))  # unchanged
    # a car's box on the truck's segment is not a truck fragment
    boxes = np.stack([FRONT, BACK])
    assert join_truck_fragments(boxes, np.array([0.8, 0.4]), np.array([True, False]), segments)[1].all()
    # two boxes with no column in common are two things on one segment, not two halves
    left, right = np.array([99.5, 49.5, 120.5, 80.5]), np.array([140.5, 49.5, 160.5, 80.5])
    boxes = np.stack([left, right])
    assert join_truck_fragments(boxes, np.array([0.8, 0.4]), np.array([True, True]), segments)[1].all()


def test_a_union_reaching_beyond_the_segment_is_not_joined():
    segments = _segments([TRUCK])
    wide = np.array([124.5, 49.5, 170.5, 80.5])  # its core is the truck's, its right side 10 px beyond
    assert core_segment(wide, segments) == 1
    joined, keep = join_truck_fragments(np.stack([FRONT, wide]), np.array([0.8, 0.4]), np.array([True, True]),
                                        segments)
    assert keep.all()
    np.testing.assert_allclose(joined[0], FRONT)


def test_the_cores_segment_pixels_decide_and_a_core_without_any_has_none():
    segments = _segments([TRUCK, (161, 50, 170, 80), (171, 50, 180, 80)])
    # a core over the truck's last 6 columns and 20 columns of two other segments: none has half
    assert core_segment(np.array([139.5, 49.5, 199.5, 80.5]), segments) == 0
    # the same core without the two: the truck's 6 columns are all the segment pixels it holds
    assert core_segment(np.array([139.5, 49.5, 199.5, 80.5]), _segments([TRUCK])) == 1
    assert core_segment(np.array([10.5, 10.5, 40.5, 30.5]), segments) == 0  # no segment pixel
    assert core_segment(np.array([120.0, 0.0, 140.0, 8.0]), segments) == 0  # above the segments' rows
