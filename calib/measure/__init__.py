"""Measurements: the dataset file and joint-unit conversion."""
