"""Files and package data: resource lookup, YAML and CSV plumbing. Imports nothing else in calib."""
