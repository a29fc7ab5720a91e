"""Fitting: registration, offset fits, posterior sampling, identification, model choice, metrics, results."""
