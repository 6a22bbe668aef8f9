"""Figures from result objects (matplotlib imported lazily, Agg backend)."""
