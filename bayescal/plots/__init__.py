"""Figures (matplotlib, Agg backend, imported lazily); each function takes a result object."""
