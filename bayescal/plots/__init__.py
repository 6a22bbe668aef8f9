"""Figures: matplotlib imported lazily (Agg) inside each function; modules take result objects."""
