"""Real trajectory recordings (NGSIM, highD) replayed as cloud twins: readers and the dataset import."""
