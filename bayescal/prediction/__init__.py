"""Prediction of new recordings from a calibrated machine, with its uncertainty (FORMATS.md section 8)."""
