"""Offline replays of a dataset through the runtime: the replay itself, its JSON report, fault
injection, per-frame overlay pictures and the progress display.
"""
