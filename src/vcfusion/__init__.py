"""vcfusion: vision-cloud data fusion co-simulation for ADAS research."""

__version__ = "0.1.0"
