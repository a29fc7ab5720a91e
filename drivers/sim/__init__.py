"""The simulated cell: one truth model that every fake device reads from or writes to."""
