"""Simulators that write drive logs with ground truth (the project's main test bed)."""
