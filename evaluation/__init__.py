"""Evaluation over a flight folder: orbit and tracking figures, accuracy against the simulator's truth."""
