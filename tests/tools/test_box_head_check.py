"""tools/box_head_check.py: the summary groups box pairs by the ground truth's height and counts the
shares at IoU >= 0.7 before and after the head; the pooled row holds the far boxes only."""


import numpy as np

from support.tool_modules import load_tool





def test_summary_groups_by_height_and_pools_the_far_boxes():
    tool = load_tool("box_head_check")
    # (ground-truth height px, IoU as detected, IoU after the head)
    pairs = np.array([[10.0, 0.6, 0.8], [12.0, 0.8, 0.75], [40.0, 0.5, 0.9], [90.0, 0.9, 0.6]])
    lines = tool.summary_lines(pairs)
    by_name = {line.split(" n=")[0].strip(): line for line in lines}
    assert set(by_name) == {"0-15 px", "30-60 px", "60-120 px", "pooled <= 60 px"}
    assert "n=   2: IoU 0.700 -> 0.775; >= 0.7 50.0% -> 100.0%" in by_name["0-15 px"]
    # the 90 px box is not a far box: the pooled row has the other three
    assert "n=   3: IoU 0.633 -> 0.817; >= 0.7 33.3% -> 100.0%" in by_name["pooled <= 60 px"]
    assert ">= 0.7 100.0% -> 0.0%" in by_name["60-120 px"]
