"""Ego camera vision: rendering, detection, depth evaluation, vision-cloud matching, AR overlay."""
