"""Calibration results as configuration blocks (YAML) and the plots a field team checks them with.
"""
