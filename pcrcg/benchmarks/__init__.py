"""Benchmarks that print figures: ``python -m pcrcg.benchmarks.<name>``.

Speed targets are shown here, never asserted by tests. ``registration``: registration seconds per
pair for each N, ours against Predator's evaluation path and against Open3D's RANSAC on identical
correspondences.
"""
