"""Figures (matplotlib, imported lazily, Agg backend); computing lives elsewhere."""
