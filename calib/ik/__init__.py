"""Inverse kinematics: closed-form (SRS, spherical wrist, subproblems) and numeric solvers."""
