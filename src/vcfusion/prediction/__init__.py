"""Lane-change prediction (paper Section IV): features, time-window labels, datasets, MLP,
smoothing (Algorithms 3 and 4), evaluation and the cloud process model."""
