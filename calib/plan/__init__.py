"""Pose plans: pose generation, observability and identifiability of a plan, socket poses."""
