"""Per-trip metrics of the ego: MOVESTAR fuel/emissions, TTC, acceleration, jerk; the cluster
bootstrap of the studies' intervals."""
