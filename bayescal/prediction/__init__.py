"""Prediction of new recordings from a calibrated machine, with its uncertainty (docs/formats.md section 8)."""
