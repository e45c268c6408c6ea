"""Vision-cloud fusion stage: box refinement by depth, depth evaluation (Alg. 1), matching twins to boxes (Alg. 2 and the
joint matcher), the AR overlay and the guidance handed to the driver."""
