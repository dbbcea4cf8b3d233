"""Benchmarks that print figures: filter steps, replay speed, camera work, latency, memory, faults.
"""
