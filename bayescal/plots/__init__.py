"""Figures (matplotlib, Agg backend, imported lazily); each function takes result objects and writes files."""
