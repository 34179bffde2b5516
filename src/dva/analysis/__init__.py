"""Analyses and benchmarks of the tasks, renderer and algorithms."""
